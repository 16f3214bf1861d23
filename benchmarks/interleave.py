"""Timing shared by the benchmarks that compare settings on one machine: rounds that alternate between the
settings, so that background load (training workers, other jobs) hits them alike, and medians with spread."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def interleaved(settings: dict[str, Callable[[], object]], repeats: int) -> dict[str, list[float]]:
    """Seconds of each setting's call, `repeats` rounds, one call of every setting per round."""
    times: dict[str, list[float]] = {name: [] for name in settings}
    for _ in range(repeats):
        for name, call in settings.items():
            t = time.perf_counter()
            call()
            times[name].append(time.perf_counter() - t)
    return times


def print_medians(times: dict[str, list[float]], base: str) -> None:
    """Each setting's median seconds, spread, and ratio to the median of setting `base`."""
    ref = statistics.median(times[base])
    width = max(map(len, times))
    for name, ts in times.items():
        m = statistics.median(ts)
        print(f"  {name:<{width}}  median {m:7.3f} s  (min {min(ts):.3f}, max {max(ts):.3f})  {m / ref:5.2f}x {base}")
