"""What every fitter needs to know about a run besides its own hyperparameters: the budget's epochs
and batch size, the seed, the device and the logger (lightning-hydra-template passes the same through
its `Trainer`). Built once per fold from the run's `budget`, `trainer` and `seed`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from meshseg.errors import ConfigError

# The Lightning precisions meshseg trains with on a CPU. Not 16-mixed: Lightning silently runs bf16-mixed for
# it on a CPU. Not 16-true, bf16-true or 64-true: they turn the weights themselves to that dtype, and prediction
# feeds float32 and reads float32 back (the 1D CNN casts its input, but its bf16 probabilities fail to convert;
# an autoencoder's float32 codes fail to multiply with float16/float64 weights).
CPU_PRECISIONS = ("32-true", "bf16-mixed")
_ALIASES = {"32": "32-true"}  # Lightning's other spelling of 32-true (also the int 32)
BF16_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")  # x86 /proc/cpuinfo flags; "bf16" is aarch64's


@dataclass(frozen=True)
class TrainContext:
    epochs: int  # passes over the training faces, per network stage
    batch_size: int
    seed: int = 0
    resample: str = "fold"  # fold: one sample of training faces for all epochs | epoch: a fresh sample each epoch
    accelerator: str = "cpu"  # cpu | gpu
    devices: int | str = 1
    precision: str | int = "32-true"  # Lightning's; on a CPU 32-true or bf16-mixed (check_precision)
    threads: int | None = None  # torch intra-op threads; also a forest's n_jobs (None: all cores)
    predict_batch_size: int = 4096
    progress_bar: bool = False
    logger: object | None = None  # a Lightning logger (the run's MLflow logger), or None
    checkpoint_dir: str | None = None  # per-epoch checkpoints of each stage here (a killed fold resumes), or none

    @classmethod
    def from_config(cls, budget, trainer, seed: int, logger=None, checkpoint_dir: str | None = None) -> TrainContext:
        """From the run's `budget` and `trainer` config nodes."""
        return cls(
            epochs=int(budget.epochs),
            batch_size=int(budget.batch_size),
            seed=int(seed),
            resample=str(budget.get("resample", "fold")),
            accelerator=str(trainer.accelerator),
            devices=trainer.devices,
            precision=check_precision(trainer.precision, str(trainer.accelerator)),
            threads=None if trainer.threads is None else int(trainer.threads),
            predict_batch_size=int(trainer.predict_batch_size),
            progress_bar=bool(trainer.progress_bar),
            logger=logger,
            checkpoint_dir=checkpoint_dir,
        )

    @property
    def device(self) -> torch.device:
        return torch.device("cuda") if self.accelerator == "gpu" else torch.device("cpu")


def cpu_bf16_flags(cpuinfo: str | Path = "/proc/cpuinfo") -> list[str]:
    """The bf16 instruction sets this CPU announces in /proc/cpuinfo (empty where it has none, or on a system
    without that file). torch.backends.cpu.get_cpu_capability() cannot tell: it says AVX512 with or without bf16.
    """
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return []
    flags = {f for line in text.splitlines() if line.startswith(("flags", "Features")) for f in line.split()}
    return [f for f in BF16_FLAGS if f in flags]


def check_precision(precision: str | int, accelerator: str) -> str | int:
    """`trainer.precision` checked for a CPU run, its canonical name returned; other accelerators' choices are
    Lightning's to check. bf16-mixed needs bf16 arithmetic in hardware (AVX512_BF16 or AMX): on an AVX2 CPU
    PyTorch runs bf16 convolutions and matmuls in its slow reference kernels, and the 1D CNN trains at 0.12-0.14x
    its 32-true samples/s (benchmarks/train_throughput.py, 1-4 branches, AMD EPYC, 2026-11-25)."""
    if accelerator != "cpu":
        return precision
    precision = _ALIASES.get(str(precision), precision)
    if precision not in CPU_PRECISIONS:
        raise ConfigError(
            f"trainer.precision={precision} is not allowed with trainer.accelerator=cpu: choose one of "
            f"{list(CPU_PRECISIONS)}"
        )
    if precision == "bf16-mixed" and not cpu_bf16_flags():
        raise ConfigError(
            f"trainer.precision=bf16-mixed is not allowed on this CPU: it lacks AVX512_BF16/AMX (torch CPU "
            f"capability {torch.backends.cpu.get_cpu_capability()}, no {'/'.join(BF16_FLAGS)} in /proc/cpuinfo), "
            "so bf16 would be emulated, slower than 32-true"
        )
    return precision
