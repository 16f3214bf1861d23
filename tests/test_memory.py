"""A run's peak resident memory: it sees an allocation, and a reset forgets an earlier one."""

import mmap
import sys

import numpy as np
import pytest

from meshseg.memory import peak_mib, reset_peak

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the kernel's high-water mark: Linux")


def test_peak_sees_an_allocation_and_a_reset_forgets_it():
    assert reset_peak()
    before = peak_mib()
    # fresh pages from the kernel: malloc could hand back memory an earlier test left resident in its heap
    block = mmap.mmap(-1, 200 << 20)
    np.frombuffer(block, dtype=np.uint8)[:] = 1  # every page touched
    assert peak_mib() >= before + 190
    block.close()
    assert peak_mib() >= before + 190  # a peak stays after the memory is freed ...
    assert reset_peak()
    assert peak_mib() < before + 60  # ... until the next run resets it
