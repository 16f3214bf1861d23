"""The paper's autoencoder baselines (§3.3) as fitters: stacked autoencoders pre-trained one after the
other, then a softmax layer and fine-tuning of the whole stack (`AutoencoderSoftmax`, "AE & NN") or a
random forest on the codes (`AutoencoderForest`, "AE & RF").

Networks train with Lightning, one Trainer per stage, every stage for the budget's epochs; their curves
go to the run's logger under the stage's name (`train/ae1_loss`, `train/ae2_loss`, `train/softmax_loss`,
and the fine-tuning's `train/loss` as for the CNN).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytorch_lightning as pl
import torch
import torch.nn.functional as F
from torch import nn

from meshseg.errors import ConfigError
from meshseg.models.autoencoder import Autoencoder, StackedAutoencoderClassifier, kl_sparsity
from meshseg.models.settings import ForestSettings
from meshseg.training.context import TrainContext
from meshseg.training.data import TrainSet
from meshseg.training.fitters import Fitter, make_forest
from meshseg.training.loop import train_stage, transform
from meshseg.training.module import StageSegmenter


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
            logged[f"train/{self.stage}_mse"] = mse.detach()
        logged[f"train/{self.stage}_loss"] = loss.detach()
        self.log_dict(logged, on_step=False, on_epoch=True, batch_size=len(x))
        return loss

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=self.lr, weight_decay=self.weight_decay)


def pretrain_autoencoders(train: TrainSet, cfg, ctx: TrainContext) -> tuple[list[Autoencoder], np.ndarray]:
    """Autoencoders of cfg.hidden sizes, each trained on the previous one's codes (the first on the
    inputs); returns them and the last one's codes of the training faces."""
    autoencoders, X = [], train.X
    for i, hidden in enumerate(cfg["hidden"], start=1):
        ae = Autoencoder(int(np.prod(X.shape[1:])), hidden, cfg["activation"], cfg["decoder_activation"])
        module = Reconstruction(
            ae,
            f"ae{i}",
            sparsity_weight=cfg["sparsity_weight"],
            sparsity_target=cfg["sparsity_target"],
            **cfg["optim"],
        )
        train_stage(module, dataclasses.replace(train, X=X), ctx, f"ae{i}")
        X = transform(ae.encoder, X.reshape(len(X), -1), ctx.predict_batch_size, ctx.device)
        autoencoders.append(ae)
    return autoencoders, X


class AutoencoderSoftmax(Fitter):
    """ "AE & NN": the autoencoders, a softmax layer trained on the codes, then the stack fine-tuned
    with cross-entropy. `softmax.optim` and `finetune.optim`: Segmenter's SGD settings."""

    def __init__(self, autoencoders: dict, softmax: dict, finetune: dict, context: TrainContext):
        super().__init__(context)
        self.autoencoders, self.softmax, self.finetune = autoencoders, softmax, finetune

    def fit(self, train: TrainSet) -> AutoencoderSoftmax:
        ctx = self.context
        autoencoders, codes = pretrain_autoencoders(train, self.autoencoders, ctx)
        net = StackedAutoencoderClassifier([ae.encoder for ae in autoencoders], codes.shape[1], train.n_classes)
        softmax = StageSegmenter(net.softmax, ctx.epochs, "softmax_", **self.softmax["optim"])
        train_stage(softmax, dataclasses.replace(train, X=codes), ctx, "softmax")
        self.module_ = StageSegmenter(net, ctx.epochs, "", **self.finetune["optim"])
        train_stage(self.module_, train, ctx, "finetune")
        self.module_.to(ctx.device)
        self.parts_ = {**{f"ae{i}": ae for i, ae in enumerate(autoencoders, start=1)}, "net": net}
        self.epochs_ = ctx.epochs * (len(autoencoders) + 2)
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        return self.module_.predict_proba(X, self.context.predict_batch_size)


class AutoencoderForest(Fitter):
    """ "AE & RF": the autoencoders (pre-trained, not fine-tuned), then a random forest on the codes."""

    epochs_trained = False  # its forest fits once on the codes

    def __init__(self, autoencoders: dict, forest: dict, context: TrainContext):
        super().__init__(context)
        self.autoencoders, self.forest = autoencoders, dict(forest)
        ForestSettings.of(self.forest)  # checked when the method is built

    def fit(self, train: TrainSet) -> AutoencoderForest:
        ctx = self.context
        autoencoders, codes = pretrain_autoencoders(train, self.autoencoders, ctx)
        self.encoder_ = nn.Sequential(*[ae.encoder for ae in autoencoders])
        self.forest_ = make_forest(self.forest, train.n_classes, ctx).fit(codes, train.y)
        self.parts_ = {
            **{f"ae{i}": ae for i, ae in enumerate(autoencoders, start=1)},
            "encoder": self.encoder_,
            "forest": self.forest_,
        }
        self.epochs_ = ctx.epochs * len(autoencoders)
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        codes = transform(self.encoder_, X.reshape(len(X), -1), self.context.predict_batch_size, self.context.device)
        return self.forest_.predict_proba(codes)
