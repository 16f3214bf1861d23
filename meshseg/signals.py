"""Signals while a fold runs: SIGTERM (`scancel`, `kill`, a job's time limit) and Ctrl-C interrupt it, so
that its run ends KILLED instead of staying RUNNING (submitit's jobs ignore SIGTERM, and SLURM follows it
with SIGKILL)."""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager


@contextmanager
def terminate_interrupts():
    """SIGTERM and SIGINT interrupt the fold: an interrupt waits for the store call under way, if any
    (meshseg.tracking.interrupt). Signals reach the main thread only; elsewhere this does nothing."""
    from meshseg.tracking import interrupt

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        interrupt(f"{signal.Signals(signum).name} received")

    previous = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
