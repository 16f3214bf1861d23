"""The Lightning module that trains any per-face network with the paper's optimiser (§3.4): SGD with
momentum, cross-entropy, and a per-epoch learning rate log-spaced from lr_start to lr_end."""

from __future__ import annotations

import numpy as np
import pytorch_lightning as pl
import torch
import torch.nn.functional as F
from torch import nn


def log_space_lr(epoch: int, epochs: int, lr_start: float, lr_end: float) -> float:
    """Learning rate of `epoch` (0-based): lr_start at the first epoch, lr_end at the last."""
    return lr_start * (lr_end / lr_start) ** (epoch / max(epochs - 1, 1))


class Segmenter(pl.LightningModule):
    def __init__(
        self,
        net: nn.Module,
        epochs: int,
        lr_start: float = 1e-2,
        lr_end: float = 1e-4,
        momentum: float = 0.9,
        weight_decay: float = 0.0,
    ):
        super().__init__()
        self.net = net
        self.epochs, self.lr_start, self.lr_end = int(epochs), float(lr_start), float(lr_end)
        self.momentum, self.weight_decay = float(momentum), float(weight_decay)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    def training_step(self, batch, batch_idx):
        x, y = batch
        logits = self.net(x)
        loss = F.cross_entropy(logits, y)
        acc = (logits.detach().argmax(1) == y).float().mean()
        self.log_dict({"train/loss": loss.detach(), "train/acc": acc}, on_step=False, on_epoch=True, batch_size=len(y))
        return loss

    def on_train_epoch_start(self) -> None:
        self.log("train/lr", self.optimizers().param_groups[0]["lr"], on_step=False, on_epoch=True)

    def configure_optimizers(self):
        opt = torch.optim.SGD(
            self.parameters(), lr=self.lr_start, momentum=self.momentum, weight_decay=self.weight_decay
        )
        factor = lambda epoch: log_space_lr(epoch, self.epochs, self.lr_start, self.lr_end) / self.lr_start  # noqa: E731
        return {
            "optimizer": opt,
            "lr_scheduler": {"scheduler": torch.optim.lr_scheduler.LambdaLR(opt, factor), "interval": "epoch"},
        }

    @torch.no_grad()
    def predict_proba(self, X: np.ndarray, batch_size: int = 2048) -> np.ndarray:
        """Class probabilities (n, classes) float32 for inputs X (n, ...), in eval mode, computed in float32
        whatever `trainer.precision` trained the network."""
        was_training = self.training
        self.eval()
        # float32 also after bf16-mixed training, and never inside an autocast region: Lightning's autocast wraps
        # only its own steps, and the weights it trained are float32 anyway; bf16 here would only add rounding
        # noise to the probabilities the graph cut reads, for about 4 % of a fold's time, and a model trained in
        # bf16 predicts the same on any CPU (meshseg.predict), with bf16 arithmetic or not.
        try:
            with torch.autocast(self.device.type, enabled=False):
                out = [
                    torch.softmax(self.net(torch.from_numpy(X[i : i + batch_size]).to(self.device)), dim=1).cpu()
                    for i in range(0, len(X), batch_size)
                ]
        finally:
            self.train(was_training)
        return torch.cat(out).numpy().astype(np.float32, copy=False)


class StageSegmenter(Segmenter):
    """Segmenter whose logged names carry a stage prefix (a multi-stage fitter's softmax stage:
    `train/softmax_loss`)."""

    def __init__(self, net: nn.Module, epochs: int, prefix: str = "", **optim):
        super().__init__(net, epochs, **optim)
        self.prefix = prefix

    def log(self, name, value, *args, **kwargs):
        return super().log(name.replace("train/", "train/" + self.prefix, 1), value, *args, **kwargs)
