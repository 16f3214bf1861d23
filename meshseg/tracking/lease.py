"""Leases: a claimed run (Tracker.claim) is RUNNING under a lease its process keeps fresh with a heartbeat
tag; a lease whose heartbeat went stale, or whose process on this host is gone, is dead and its config
can be taken over."""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from dataclasses import dataclass

log = logging.getLogger(__name__)

#: lease tags of a claimed run: who runs it, when it last said so, and the timing
LEASE_OWNER, LEASE_HEARTBEAT = "lease.owner", "lease.heartbeat"
LEASE_TIMEOUT, LEASE_INTERVAL = "lease.timeout_s", "lease.interval_s"


@dataclass(frozen=True)
class Lease:
    """A claim's timing: the heartbeat's interval, and the age at which a silent lease is dead
    (`tracking.heartbeat_s`, `tracking.lease_timeout_s`)."""

    heartbeat_s: float = 30.0
    timeout_s: float = 120.0

    def tags(self) -> dict[str, str]:
        """The lease tags of a run claimed now by this process."""
        return {
            LEASE_OWNER: owner(),
            LEASE_HEARTBEAT: f"{time.time():.0f}",
            LEASE_TIMEOUT: f"{self.timeout_s:g}",
            LEASE_INTERVAL: f"{self.heartbeat_s:g}",
        }


def owner() -> str:
    """This process, as a lease names it: host:pid."""
    return f"{socket.gethostname()}:{os.getpid()}"


def holds(run) -> bool:
    """Whether a run keeps its config from others: it is FINISHED, or RUNNING under a live lease."""
    return run.info.status == "FINISHED" or (run.info.status == "RUNNING" and lease_alive(run))


def holder(runs: list):
    """The run that keeps the config among `runs` (a FINISHED one first, then the earliest), or None."""
    held = [r for r in runs if holds(r)]
    return min(held, key=lambda r: (r.info.status != "FINISHED", r.info.start_time)) if held else None


def lease_alive(run) -> bool:
    """Whether a RUNNING run's process is still at work: its heartbeat is recent and, when it runs on
    this host, its process exists (so a run killed outright here is taken over at once)."""
    tags = run.data.tags
    try:
        age = time.time() - float(tags[LEASE_HEARTBEAT])
        timeout = float(tags.get(LEASE_TIMEOUT, 120))
    except (KeyError, ValueError):
        return False  # no lease: a run from before leases, or a damaged one
    host, _, pid = tags.get(LEASE_OWNER, "").rpartition(":")
    if host == socket.gethostname() and pid.isdigit():
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            pass  # it exists, under another user
    return age < timeout


def take_over(client, stale: list, run_id: str) -> None:
    """Mark the RUNNING ones of `stale` (their processes died mid-run) KILLED, superseded by `run_id`."""
    for run in stale:
        if run.info.status == "RUNNING":
            client.set_tag(run.info.run_id, "superseded_by", run_id)
            client.set_terminated(run.info.run_id, "KILLED")


class Heartbeat:
    """A daemon thread that refreshes a run's heartbeat tag every lease interval until stopped."""

    def __init__(self, client, run_id: str):
        self.client, self.run_id = client, run_id
        self.interval = float(client.get_run(run_id).data.tags.get(LEASE_INTERVAL, 30))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat-{run_id[:8]}", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.client.set_tag(self.run_id, LEASE_HEARTBEAT, f"{time.time():.0f}")
            except Exception as e:  # a store hiccup must not kill training; the next beat retries
                log.warning("heartbeat of run %s: %s", self.run_id, e)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
