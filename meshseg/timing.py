"""Seconds per phase of a fold (features, inputs, train, predict, refine, ...), logged as `time/<phase>_s`."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager


class Timings(dict):
    """{phase: seconds}; `with timings("train"): ...` adds that block's wall time to the phase."""

    @contextmanager
    def __call__(self, phase: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self[phase] = self.get(phase, 0.0) + time.perf_counter() - t0


def time_left(elapsed_s: float, done: int, remaining: int) -> str:
    """'about 40 s left' (minutes from 2 min on): `remaining` items at the pace of the `done` items that took
    `elapsed_s`; '' where nothing is done yet to pace by. The progress lines of epochs, feature meshes and
    sweep jobs all end with it."""
    if done <= 0:
        return ""
    left = elapsed_s / done * remaining
    return f"about {left:.0f} s left" if left < 120 else f"about {left / 60:.0f} min left"
