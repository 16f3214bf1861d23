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
