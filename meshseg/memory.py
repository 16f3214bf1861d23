"""A fold's peak resident memory, logged as `memory/peak_rss_mib`: what a machine (or a SLURM `--mem`) needs
to hold the run. From the kernel's high-water mark of the process (Linux), reset when a run starts, so a
sweep's later jobs, which run in the same process, are not charged with an earlier job's peak."""

from __future__ import annotations


def reset_peak() -> bool:
    """Lower the process's peak resident memory to what it holds now (Linux 4.0 on: /proc/self/clear_refs);
    False where the kernel does not allow it, and the peak still counts from the process's start."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        return False
    return True


def peak_mib() -> float | None:
    """The process's peak resident memory in MiB (VmHWM) since it started or since `reset_peak`; None where
    /proc does not say. Memory of child processes (data loader and feature workers) is not in it."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024  # kB
    except OSError:
        pass
    return None
