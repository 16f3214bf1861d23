"""The generic Lightning plumbing every network stage shares: a Trainer as the context says, one
`fit` over a fold's training faces, and a network applied to inputs in batches."""

from __future__ import annotations

import logging
import time
import warnings
from pathlib import Path

import numpy as np
import pytorch_lightning as pl
import torch
from pytorch_lightning.callbacks import ModelCheckpoint
from pytorch_lightning.plugins.environments import LightningEnvironment
from torch import nn

from meshseg.timing import time_left
from meshseg.training.context import TrainContext
from meshseg.training.data import FoldDataModule, TrainSet

log = logging.getLogger("meshseg.training")


class EpochLog(pl.Callback):
    """One log line per epoch where no progress bar is shown: what the module logged (loss, accuracy,
    learning rate), the epoch's seconds and the time left at the pace so far."""

    def on_train_start(self, trainer, module):
        self.start = self.last = time.perf_counter()
        self.first = trainer.current_epoch  # > 0 when resumed from a checkpoint

    def on_train_epoch_end(self, trainer, module):
        now = time.perf_counter()
        took, self.last = now - self.last, now
        done, total = trainer.current_epoch + 1, trainer.max_epochs
        left = time_left(now - self.start, done - self.first, total - done)
        values = ", ".join(f"{k} {float(v):.4g}" for k, v in sorted(trainer.callback_metrics.items()) if v.numel() == 1)
        log.info("epoch %d/%d: %s; %.1f s, %s", done, total, values, took, left)


def make_trainer(ctx: TrainContext, stage: str = "net") -> pl.Trainer:
    callbacks: list[pl.Callback] = [] if ctx.progress_bar else [EpochLog()]
    if ctx.checkpoint_dir:  # the stage's state after every epoch, so a killed fold resumes where it was
        # one file, last.ckpt, rewritten every epoch (no monitor: the newest is kept)
        where = Path(ctx.checkpoint_dir) / stage
        callbacks.append(ModelCheckpoint(dirpath=where, filename="last", save_top_k=1, enable_version_counter=False))
    return pl.Trainer(
        max_epochs=ctx.epochs,
        accelerator=ctx.accelerator,
        devices=ctx.devices,
        precision=ctx.precision,
        logger=ctx.logger or False,
        enable_checkpointing=bool(ctx.checkpoint_dir),
        enable_progress_bar=ctx.progress_bar,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        log_every_n_steps=1,
        # one process per fold, also inside a SLURM job: Lightning must not take the job over (its SLURM
        # environment installs requeue signal handlers and warns when `srun` merely exists)
        plugins=[LightningEnvironment()],
        callbacks=callbacks,
    )


def train_stage(module: pl.LightningModule, data: TrainSet, ctx: TrainContext, stage: str = "net") -> None:
    """Fit `module` on `data` for the context's epochs, mini-batches shuffled with a seeded generator.
    With `ctx.checkpoint_dir`, a checkpoint of this `stage` left by a killed run is resumed from."""
    trainer = make_trainer(ctx, stage)
    last = Path(ctx.checkpoint_dir) / stage / "last.ckpt" if ctx.checkpoint_dir else None
    if last is not None and last.is_file():
        epoch = torch.load(last, map_location="cpu", weights_only=False).get("epoch", -1) + 1
        log.info("%s: resuming from its checkpoint after epoch %d/%d (%s)", stage, epoch, ctx.epochs, last)
    else:
        last = None
    with warnings.catch_warnings():
        # One in-memory tensor dataset: DataLoader worker processes would only add copies.
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*LeafSpec.*is deprecated")  # Lightning 2.6 on torch 2.13
        # fit() asks whether SLURM launched it (for its own requeue checkpoints) even with LightningEnvironment
        warnings.filterwarnings("ignore", message=".*The `srun` command is available on your system")
        try:
            trainer.fit(module, datamodule=FoldDataModule(data, ctx.batch_size, ctx.seed), ckpt_path=last)
        except SystemExit as e:
            # Lightning answers an interrupt (Ctrl-C, or SIGTERM through meshseg.run) with its own shutdown
            # and sys.exit(1); the fold must see the interrupt itself, so that its run ends KILLED, not FAILED
            if isinstance(e.__context__, KeyboardInterrupt):
                raise e.__context__ from None
            raise


@torch.no_grad()
def transform(fn: nn.Module, X: np.ndarray, batch_size: int, device: torch.device) -> np.ndarray:
    """fn applied to the rows of X in batches, in eval mode on `device`: (n, ...) float32, computed in float32
    whatever `trainer.precision` trained fn (as `Segmenter.predict_proba`, which says why)."""
    was_training = fn.training
    fn.to(device).eval()
    try:
        with torch.autocast(device.type, enabled=False):
            out = [fn(torch.from_numpy(X[i : i + batch_size]).to(device)).cpu() for i in range(0, len(X), batch_size)]
    finally:
        fn.train(was_training)  # a later stage trains these layers again
    return torch.cat(out).numpy().astype(np.float32, copy=False)
