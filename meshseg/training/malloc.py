"""glibc malloc tuning for CPU training: speed only, results are the same either way."""

from __future__ import annotations

import ctypes
import sys


def tune_glibc_malloc(mmap_threshold: int = 32 << 20, trim_threshold: int = 1 << 30) -> bool:
    """Make glibc's malloc keep freed memory for reuse rather than return it to the kernel (process-wide).

    A CPU training step allocates tens of MiB of fresh activations and gradients; with glibc's defaults
    many of their pages are unmapped at the end of the step and faulted in (and zeroed) again in the next,
    which costs this model 15-20 % of its training speed on 2 cores. This serves allocations up to
    `mmap_threshold` bytes (glibc's maximum is 32 MiB) from the heap and trims the heap only when more
    than `trim_threshold` bytes are free at its top. The environment variables MALLOC_MMAP_THRESHOLD_
    and MALLOC_TRIM_THRESHOLD_, set before the process starts, do the same (set both: either alone
    turns off glibc's adaptive threshold and makes things slower). Returns False where there is no glibc.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return False
    m_trim_threshold, m_mmap_threshold = -1, -3  # from glibc's malloc.h
    ok = libc.mallopt(m_mmap_threshold, int(mmap_threshold)) and libc.mallopt(m_trim_threshold, int(trim_threshold))
    return bool(ok)
