"""The paper's multi-branch 1D CNN (George, Xie & Tam 2018, §3.4 and its figure 3).

Per branch k = 1..B (each with its own parameters; branch k reads the multi-scale input X^k):

    Conv1d 1->16, kernel 15, "same" -> BatchNorm -> LeakyReLU(0.2) -> MaxPool 2
    Conv1d 16->32, kernel 11, "same" -> BatchNorm -> LeakyReLU(0.2) -> MaxPool 2      => 32 x D//4

then the branches' maps concatenated depth-wise (32·B channels) -> flatten -> FC 172 -> LeakyReLU(0.2)
-> Dropout 0.5 -> FC classes -> softmax (the training loss applies it as cross-entropy).

`PaperCNN1D` below is that network in plain torch.nn layers: read it to see the method. Training uses
`MultiBranchCNN1D` (meshseg/models/cnn1d_fast.py), which computes the same function, gradients and
batch-norm statistics from the same initial weights, about 1.3-1.8x faster on a few CPU cores
(tests/test_cnn1d.py checks the equivalence; benchmarks/train_throughput.py measures both).
"""

from __future__ import annotations

import torch
from torch import nn

from meshseg.models.cnn1d_fast import EVAL_CHUNK, MAX_BRANCHES, MultiBranchCNN1D, flops_per_sample

__all__ = ["PaperCNN1D", "MultiBranchCNN1D", "flops_per_sample", "EVAL_CHUNK", "MAX_BRANCHES"]


class PaperCNN1D(nn.Module):
    """The paper's network, written as the paper draws it: one nn.Sequential per branch, the branches'
    maps concatenated on the channel axis, then the fully connected head. Input (N, branches, features):
    branch k reads X^{k+1}; output logits (N, classes)."""

    def __init__(
        self,
        n_features: int,
        n_classes: int,
        branches: int = 3,
        channels=(16, 32),
        kernels=(15, 11),
        hidden: int = 172,
        negative_slope: float = 0.2,
        dropout: float = 0.5,
        pool: int = 2,
    ):
        super().__init__()

        def branch() -> nn.Sequential:
            layers, c_in = [], 1
            for c_out, k in zip(channels, kernels):
                layers += [
                    nn.Conv1d(c_in, c_out, k, padding="same"),
                    nn.BatchNorm1d(c_out),
                    nn.LeakyReLU(negative_slope),
                    nn.MaxPool1d(pool),
                ]
                c_in = c_out
            return nn.Sequential(*layers)

        self.branches = nn.ModuleList(branch() for _ in range(branches))
        length = n_features
        for _ in channels:
            length //= pool
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(branches * channels[-1] * length, hidden),
            nn.LeakyReLU(negative_slope),
            nn.Dropout(dropout),
            nn.Linear(hidden, n_classes),
        )

    def feature_maps(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([b(x[:, k : k + 1]) for k, b in enumerate(self.branches)], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.feature_maps(x))
