"""The paper's stacked autoencoders (§3.3, "AE & NN" and "AE & RF"): an autoencoder 800 -> 400, a
second one 400 -> 200 on the first one's codes, a softmax layer on the 200 codes, then the stack
encoder 1 -> encoder 2 -> softmax fine-tuned as one network.

The paper used MATLAB (trainAutoencoder / trainSoftmaxLayer / stack). Its defaults are kept where they
carry over: sigmoid (logsig) encoders and an optional KL sparsity penalty on the mean code activation;
the decoder is linear by default because the inputs are z-scores, not MATLAB's [0, 1]-rescaled data.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from meshseg.models.pca_nn import make_activation


class Autoencoder(nn.Module):
    """x (N, ...) flattened to (N, n_in) -> encoder (Linear -> activation) -> codes (N, n_hidden)
    -> decoder (Linear -> decoder_activation) -> reconstruction (N, n_in)."""

    def __init__(self, n_in: int, n_hidden: int, activation: str = "sigmoid", decoder_activation: str = "linear"):
        super().__init__()
        self.n_in, self.n_hidden, self.activation = int(n_in), int(n_hidden), activation
        self.encoder = nn.Sequential(nn.Linear(self.n_in, self.n_hidden), make_activation(activation))
        self.decoder = nn.Sequential(nn.Linear(self.n_hidden, self.n_in), make_activation(decoder_activation))

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoder(x.flatten(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.decoder(self.encode(x))


def kl_sparsity(codes: torch.Tensor, target: float) -> torch.Tensor:
    """Sum over code units of KL(target || mean activation over the batch), as MATLAB's
    SparsityRegularization: pushes each unit's average activation towards `target`. Codes in (0, 1)."""
    rho = codes.mean(dim=0).clamp(1e-6, 1 - 1e-6)
    return (target * torch.log(target / rho) + (1 - target) * torch.log((1 - target) / (1 - rho))).sum()


class StackedAutoencoderClassifier(nn.Module):
    """x (N, ...) -> encoders in turn -> codes -> Linear (the softmax layer): logits (N, n_classes).
    The caller applies softmax / cross-entropy."""

    def __init__(self, encoders: Sequence[nn.Module], n_codes: int, n_classes: int):
        super().__init__()
        self.encoders = nn.Sequential(*encoders)
        self.softmax = nn.Linear(int(n_codes), int(n_classes))

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        return self.encoders(x.flatten(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.softmax(self.encode(x))
