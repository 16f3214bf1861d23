"""The paper's "PCA & NN" baseline (§3.2): the per-face features projected onto their first 50
principal components, then a fully connected network of 50, 25 and 12 neurons and a softmax layer.

The projection is a frozen layer: `PCAProjection` holds the training faces' mean and principal axes
as buffers (saved with the network, never trained), set once per fold by `fit_pca` from the training
faces only, as scikit-learn's PCA would be (`components_`, `mean_`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from meshseg.errors import ConfigError
from meshseg.models.settings import ACTIVATIONS, PCANetSettings


def make_activation(name: str) -> nn.Module:
    """A fresh activation layer by name (one of meshseg.models.settings.ACTIVATIONS)."""
    if name not in ACTIVATIONS:
        raise ConfigError(f"activation {name!r} is not known: choose one of {sorted(ACTIVATIONS)}")
    return ACTIVATIONS[name]()


def principal_axes(X: np.ndarray, n_components: int, chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """Mean (d,) and the first `n_components` principal axes (k, d), orthonormal rows, of the rows of X.

    From the float64 covariance accumulated in chunks (memory d x d however many rows); each axis's
    sign is fixed so that its largest-magnitude entry is positive, so the result is deterministic.
    """
    n, d = X.shape
    if not 1 <= n_components <= min(n, d):
        raise ConfigError(
            f"PCA to {n_components} components needs at least that many features and training faces; "
            f"got {d} features and {n} faces"
        )
    mean = X.mean(axis=0, dtype=np.float64)
    cov = np.zeros((d, d))
    for i in range(0, n, chunk):
        c = X[i : i + chunk].astype(np.float64) - mean
        cov += c.T @ c
    values, vectors = np.linalg.eigh(cov / max(n - 1, 1))
    axes = vectors[:, ::-1][:, :n_components].T  # eigh sorts ascending
    signs = np.sign(axes[np.arange(n_components), np.abs(axes).argmax(axis=1)])
    return mean, axes * signs[:, None]


class PCAProjection(nn.Module):
    """x (N, d) -> (x - mean) @ components.T, (N, k). Buffers, not parameters: fitted, then frozen."""

    def __init__(self, n_features: int, n_components: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(int(n_features)))
        self.register_buffer("components", torch.zeros(int(n_components), int(n_features)))

    def fit(self, X: np.ndarray) -> PCAProjection:
        """Set mean and components from the rows of X (n, d): the training faces only."""
        mean, axes = principal_axes(X, self.components.shape[0])
        self.mean.copy_(torch.from_numpy(mean))
        self.components.copy_(torch.from_numpy(axes))
        return self

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) @ self.components.T


class PCANet(nn.Module):
    """Input (N, branches=1, n_features) -> PCA to `n_components` -> FC `hidden[0]` -> act -> ... ->
    FC n_classes: logits (the caller applies softmax / cross-entropy).

    The paper: 50 components, hidden (50, 25, 12), "then fed into a softmax layer"; its activation is
    not stated (MATLAB's patternnet default, tanh, is the config default).
    """

    Settings = PCANetSettings  # checked when the method is built (meshseg.training.fitters.NetFitter)

    def __init__(self, n_features: int, n_classes: int, branches: int = 1, **settings):
        super().__init__()
        s = self.settings = PCANetSettings.of(settings)
        if int(branches) != 1:
            raise ConfigError(f"branches={branches} is not allowed: PCANet takes one branch (single-scale features)")
        self.n_features = int(n_features)
        self.pca = PCAProjection(n_features, s.n_components)
        layers, width = [], s.n_components
        for h in s.hidden:
            layers += [nn.Linear(width, h), make_activation(s.activation)]
            width = h
        self.mlp = nn.Sequential(*layers, nn.Linear(width, int(n_classes)))

    def fit_frozen(self, X: np.ndarray) -> None:
        """Fit the frozen layers (the PCA) on the training inputs X (n, 1, n_features)."""
        self.pca.fit(X.reshape(len(X), -1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1:].numel() != self.n_features:
            raise ValueError(f"expected input (N, 1, {self.n_features}), got {tuple(x.shape)}")
        return self.mlp(self.pca(x.flatten(1)))
