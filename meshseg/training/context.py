"""What every fitter needs to know about a run besides its own hyperparameters: the budget's epochs
and batch size, the seed, the device and the logger (lightning-hydra-template passes the same through
its `Trainer`). Built once per fold from the run's `budget`, `trainer` and `seed`."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class TrainContext:
    epochs: int  # passes over the training faces, per network stage
    batch_size: int
    seed: int = 0
    resample: str = "fold"  # fold: one sample of training faces for all epochs | epoch: a fresh sample each epoch
    accelerator: str = "cpu"  # cpu | gpu
    devices: int | str = 1
    precision: str | int = "32-true"
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
            precision=trainer.precision,
            threads=None if trainer.threads is None else int(trainer.threads),
            predict_batch_size=int(trainer.predict_batch_size),
            progress_bar=bool(trainer.progress_bar),
            logger=logger,
            checkpoint_dir=checkpoint_dir,
        )

    @property
    def device(self) -> torch.device:
        return torch.device("cuda") if self.accelerator == "gpu" else torch.device("cpu")
