"""Where and with what a run ran: the git commit, the machine, the package versions, the SLURM job, and
MLflow's own run fields that its UI shows."""

from __future__ import annotations

import subprocess
from pathlib import Path


def system_tags(source: str, command: str, git: str) -> dict[str, str]:
    """MLflow's own run fields, which its UI shows: source, user, git commit, and the command line as the
    run's description (`mlflow.note.content`)."""
    import getpass

    try:
        user = getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (some containers)
        user = "unknown"
    sha = git.removesuffix("+dirty")
    return {
        "mlflow.source.name": source,
        "mlflow.source.type": "JOB" if slurm_job() else "LOCAL",
        "mlflow.user": user,
        **({"mlflow.source.git.commit": sha} if sha != "unknown" else {}),
        "mlflow.note.content": f"`{command}`",
    }


def slurm_job() -> str | None:
    """The SLURM job running this process (array jobs as <array job>_<task>), or None outside SLURM."""
    import os

    env = os.environ
    if env.get("SLURM_ARRAY_JOB_ID") and env.get("SLURM_ARRAY_TASK_ID"):
        return f"{env['SLURM_ARRAY_JOB_ID']}_{env['SLURM_ARRAY_TASK_ID']}"
    return env.get("SLURM_JOB_ID")


def machine(accelerator: str = "cpu") -> str:
    """What ran it: the CPU model, its cores and the vector instructions PyTorch's CPU kernels use (with bf16
    where the CPU has it in hardware), the kernels numpy's OpenBLAS chose for this CPU, and the GPU where one
    trained. Hosts with one model name differ 3x in speed by their instructions, `cpu2` (bf16-mixed) runs only
    where bf16 is in hardware, and the features differ in their last bits (curvature by up to 0.15) between
    OpenBLAS's Haswell and SkylakeX kernels, enough to move a GBDT fold by a point (docs/results.md, verify)."""
    import os
    import platform

    import torch

    from meshseg.training.context import cpu_bf16_flags

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    text = f"{cpu}, {os.cpu_count()} cores, {torch.backends.cpu.get_cpu_capability()}"
    if cpu_bf16_flags():
        text += " + bf16"
    if kernels := blas_kernels():
        text += f", OpenBLAS {kernels}"
    if accelerator == "gpu" and torch.cuda.is_available():
        text += f", {torch.cuda.get_device_name()}"
    return text


def blas_kernels() -> str | None:
    """The CPU target of the OpenBLAS numpy loaded (e.g. Haswell, SkylakeX: OPENBLAS_CORETYPE sets it), or None
    where numpy uses another BLAS."""
    import numpy  # noqa: F401  (loads its BLAS, so threadpoolctl sees it)
    from threadpoolctl import threadpool_info

    for pool in threadpool_info():
        if pool.get("internal_api") == "openblas" and "numpy" in pool.get("filepath", ""):
            return pool.get("architecture") or None
    return None


def versions() -> str:
    """The versions of Python and the packages that shape a result (LightGBM too: GBDT folds depend on it, and
    a record that does not name it cannot tell a library change from a code change)."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    out = [f"python {platform.python_version()}"]
    for name in ("meshseg", "torch", "numpy", "scipy", "scikit-learn", "pytorch-lightning", "mlflow", "lightgbm"):
        try:
            out.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            pass
    return ", ".join(out)


#: what the package writes or documents, not what runs: a run worktree whose `meshseg.reproduce` has rewritten
#: its report is still the commit's code
NOT_CODE = ("reports", "results", "docs", "notebooks")


def git_sha(root: Path | None = None) -> str:
    """The package's git commit, '+dirty' when tracked files outside `NOT_CODE` differ from it; 'unknown'
    outside git. `root`: the checkout (default: this package's)."""
    root = root or Path(__file__).resolve().parents[2]
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ".", *(f":(exclude){p}" for p in NOT_CODE)],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return sha + ("+dirty" if dirty else "")
