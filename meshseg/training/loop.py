"""The generic Lightning plumbing every network stage shares: a Trainer as the context says, one
`fit` over a fold's training faces, and a network applied to inputs in batches."""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np
import pytorch_lightning as pl
import torch
from pytorch_lightning.plugins.environments import LightningEnvironment
from torch import nn

from meshseg.training.context import TrainContext
from meshseg.training.data import FoldDataModule, TrainSet

log = logging.getLogger("meshseg.training")


class EpochLog(pl.Callback):
    """One log line per epoch where no progress bar is shown: what the module logged (loss, accuracy,
    learning rate), the epoch's seconds and the time left at the pace so far."""

    def on_train_start(self, trainer, module):
        self.start = self.last = time.perf_counter()

    def on_train_epoch_end(self, trainer, module):
        now = time.perf_counter()
        took, self.last = now - self.last, now
        done, total = trainer.current_epoch + 1, trainer.max_epochs
        left = (now - self.start) / done * (total - done)
        values = ", ".join(f"{k} {float(v):.4g}" for k, v in sorted(trainer.callback_metrics.items()) if v.numel() == 1)
        log.info("epoch %d/%d: %s; %.1f s, about %.0f s left", done, total, values, took, left)


def make_trainer(ctx: TrainContext) -> pl.Trainer:
    return pl.Trainer(
        max_epochs=ctx.epochs,
        accelerator=ctx.accelerator,
        devices=ctx.devices,
        precision=ctx.precision,
        logger=ctx.logger or False,
        enable_checkpointing=False,
        enable_progress_bar=ctx.progress_bar,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        log_every_n_steps=1,
        # one process per fold, also inside a SLURM job: Lightning must not take the job over (its SLURM
        # environment installs requeue signal handlers and warns when `srun` merely exists)
        plugins=[LightningEnvironment()],
        callbacks=[] if ctx.progress_bar else [EpochLog()],
    )


def train_stage(module: pl.LightningModule, data: TrainSet, ctx: TrainContext) -> None:
    """Fit `module` on `data` for the context's epochs, mini-batches shuffled with a seeded generator."""
    trainer = make_trainer(ctx)
    with warnings.catch_warnings():
        # One in-memory tensor dataset: DataLoader worker processes would only add copies.
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*LeafSpec.*is deprecated")  # Lightning 2.6 on torch 2.13
        # fit() asks whether SLURM launched it (for its own requeue checkpoints) even with LightningEnvironment
        warnings.filterwarnings("ignore", message=".*The `srun` command is available on your system")
        trainer.fit(module, datamodule=FoldDataModule(data, ctx.batch_size, ctx.seed))


@torch.no_grad()
def transform(fn: nn.Module, X: np.ndarray, batch_size: int, device: torch.device) -> np.ndarray:
    """fn applied to the rows of X in batches, in eval mode on `device`: (n, ...) float32."""
    was_training = fn.training
    fn.to(device).eval()
    try:
        out = [fn(torch.from_numpy(X[i : i + batch_size]).to(device)).cpu() for i in range(0, len(X), batch_size)]
    finally:
        fn.train(was_training)  # a later stage trains these layers again
    return torch.cat(out).numpy().astype(np.float32, copy=False)
