"""Multi-stage fitting of the paper's baselines (§3.3): stacked autoencoders pre-trained one after the
other, then a softmax layer and fine-tuning of the whole stack ("AE & NN") or a random forest on the
codes ("AE & RF"); and a random forest on the features themselves (the CF figure).

Each `fit_*` takes a fold's `TrainSet` and returns a `Fitted`: the trained parts by stage name and a
function giving class probabilities (n, classes) float32 for standardised inputs (n, 1, features).
Networks train with Lightning, one Trainer per stage, every stage for the budget's epochs; their curves
go to the run's logger under the stage's name (`ae1_loss`, `ae2_loss`, `softmax_train_loss`, and the
fine-tuning's `train_loss` as for the CNN).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytorch_lightning as pl
import torch
import torch.nn.functional as F
from torch import nn

from meshseg.errors import ConfigError
from meshseg.models.autoencoder import Autoencoder, StackedAutoencoderClassifier, kl_sparsity
from meshseg.models.forest import RandomForest
from meshseg.training.data import FoldDataModule, TrainSet
from meshseg.training.module import Segmenter


@dataclass
class Fitted:
    parts: dict[str, object]  # trained parts by stage name (ae1, ae2, net, forest, ...)
    predict_proba: Callable[[np.ndarray], np.ndarray]  # standardised inputs (n, 1, d) -> (n, classes) float32
    epochs: int  # passes over the training faces, all network stages


def make_trainer(trainer_cfg, epochs: int, logger=None) -> pl.Trainer:
    return pl.Trainer(
        max_epochs=int(epochs),
        accelerator=trainer_cfg.accelerator,
        devices=trainer_cfg.devices,
        precision=trainer_cfg.precision,
        logger=logger or False,
        enable_checkpointing=False,
        enable_progress_bar=trainer_cfg.progress_bar,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        log_every_n_steps=1,
    )


def train_stage(module: pl.LightningModule, data: TrainSet, budget, trainer_cfg, seed: int, logger=None) -> None:
    """Fit `module` on `data` for the budget's epochs, mini-batches shuffled with a seeded generator."""
    trainer = make_trainer(trainer_cfg, budget.epochs, logger)
    with warnings.catch_warnings():
        # One in-memory tensor dataset: DataLoader worker processes would only add copies.
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*LeafSpec.*is deprecated")  # Lightning 2.6 on torch 2.13
        trainer.fit(module, datamodule=FoldDataModule(data, budget.batch_size, seed))


def device_of(trainer_cfg) -> torch.device:
    return torch.device("cuda") if trainer_cfg.accelerator == "gpu" else torch.device("cpu")


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


class StageSegmenter(Segmenter):
    """Segmenter (cross-entropy, SGD with log-spaced learning rate) whose logged names carry a stage prefix."""

    def __init__(self, net: nn.Module, epochs: int, prefix: str = "", **optim):
        super().__init__(net, epochs, **optim)
        self.prefix = prefix

    def log(self, name, value, *args, **kwargs):
        return super().log(self.prefix + name, value, *args, **kwargs)


class Reconstruction(pl.LightningModule):
    """Pre-trains one autoencoder: mean squared reconstruction error (+ sparsity_weight x KL sparsity
    of the codes), Adam with a constant learning rate. Logs `<stage>_loss` per epoch (and `<stage>_mse`
    when the sparsity penalty is on)."""

    def __init__(
        self,
        autoencoder: Autoencoder,
        stage: str,
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        sparsity_weight: float = 0.0,
        sparsity_target: float = 0.05,
    ):
        super().__init__()
        if sparsity_weight > 0 and autoencoder.activation != "sigmoid":
            raise ConfigError(
                f"sparsity_weight > 0 needs sigmoid codes in (0, 1), got activation {autoencoder.activation!r}"
            )
        self.autoencoder, self.stage = autoencoder, stage
        self.lr, self.weight_decay = float(lr), float(weight_decay)
        self.sparsity_weight, self.sparsity_target = float(sparsity_weight), float(sparsity_target)

    def training_step(self, batch, batch_idx):
        x, _ = batch
        x = x.flatten(1)
        codes = self.autoencoder.encode(x)
        mse = F.mse_loss(self.autoencoder.decoder(codes), x)
        loss, logged = mse, {}
        if self.sparsity_weight:
            loss = mse + self.sparsity_weight * kl_sparsity(codes, self.sparsity_target)
            logged[f"{self.stage}_mse"] = mse.detach()
        logged[f"{self.stage}_loss"] = loss.detach()
        self.log_dict(logged, on_step=False, on_epoch=True, batch_size=len(x))
        return loss

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=self.lr, weight_decay=self.weight_decay)


def pretrain_autoencoders(
    train: TrainSet, cfg, budget, trainer_cfg, seed: int, logger=None
) -> tuple[list[Autoencoder], np.ndarray]:
    """Autoencoders of cfg.hidden sizes, each trained on the previous one's codes (the first on the
    inputs); returns them and the last one's codes of the training faces."""
    device, batch = device_of(trainer_cfg), int(trainer_cfg.predict_batch_size)
    autoencoders, X = [], train.X
    for i, hidden in enumerate(cfg.hidden, start=1):
        ae = Autoencoder(int(np.prod(X.shape[1:])), hidden, cfg.activation, cfg.decoder_activation)
        module = Reconstruction(
            ae, f"ae{i}", sparsity_weight=cfg.sparsity_weight, sparsity_target=cfg.sparsity_target, **cfg.optim
        )
        train_stage(
            module, TrainSet(X, train.y, train.standardiser, train.mesh_faces), budget, trainer_cfg, seed, logger
        )
        X = transform(ae.encoder, X.reshape(len(X), -1), batch, device)
        autoencoders.append(ae)
    return autoencoders, X


def make_forest(forest_cfg, n_classes: int, trainer_cfg, seed: int) -> RandomForest:
    """The configured forest; its worker count is the trainer's thread count (all cores when null)."""
    return RandomForest(n_classes, **forest_cfg, n_jobs=trainer_cfg.threads or -1, seed=seed)


def fit_autoencoder(train: TrainSet, n_classes: int, model_cfg, budget, trainer_cfg, seed: int, logger=None) -> Fitted:
    """`head: softmax`: autoencoders, softmax on the codes, stack fine-tuned ("AE & NN").
    `head: forest`: autoencoders, random forest on the codes ("AE & RF")."""
    if model_cfg.head not in ("softmax", "forest"):
        raise ConfigError(f"model {model_cfg.name}: head={model_cfg.head!r} is not known: choose softmax or forest")
    device, batch = device_of(trainer_cfg), int(trainer_cfg.predict_batch_size)
    autoencoders, codes = pretrain_autoencoders(train, model_cfg.autoencoders, budget, trainer_cfg, seed, logger)
    parts: dict[str, object] = {f"ae{i}": ae for i, ae in enumerate(autoencoders, start=1)}
    encoders = [ae.encoder for ae in autoencoders]
    if model_cfg.head == "forest":
        encoder = nn.Sequential(*encoders)
        forest = make_forest(model_cfg.forest, n_classes, trainer_cfg, seed).fit(codes, train.y)
        parts.update(encoder=encoder, forest=forest)
        predict = lambda X: forest.predict_proba(transform(encoder, X.reshape(len(X), -1), batch, device))  # noqa: E731
        return Fitted(parts, predict, budget.epochs * len(autoencoders))

    net = StackedAutoencoderClassifier(encoders, codes.shape[1], n_classes)
    softmax = StageSegmenter(net.softmax, budget.epochs, "softmax_", **model_cfg.softmax.optim)
    train_stage(
        softmax, TrainSet(codes, train.y, train.standardiser, train.mesh_faces), budget, trainer_cfg, seed, logger
    )
    finetune = StageSegmenter(net, budget.epochs, "", **model_cfg.finetune.optim)
    train_stage(finetune, train, budget, trainer_cfg, seed, logger)
    finetune.to(device)
    parts["net"] = net
    return Fitted(parts, lambda X: finetune.predict_proba(X, batch), budget.epochs * (len(autoencoders) + 2))


def fit_forest(train: TrainSet, n_classes: int, model_cfg, budget, trainer_cfg, seed: int, logger=None) -> Fitted:
    """A random forest on the (standardised, single-scale) features of the training faces."""
    forest = make_forest(model_cfg.forest, n_classes, trainer_cfg, seed).fit(train.X, train.y)
    return Fitted({"forest": forest}, forest.predict_proba, 1)
