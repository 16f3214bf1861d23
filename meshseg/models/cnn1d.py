"""The paper's multi-branch 1D CNN (George, Xie & Tam 2018, §3.4 and its figure 3): the one description
of the network; its settings are `CNN1DSettings` (meshseg/models/settings.py, conf/model/cnn1d.yaml).

Per branch k = 1..B (each with its own parameters; branch k reads the multi-scale input X^k of length D):

    Conv1d 1->16, kernel 15, "same" -> BatchNorm -> LeakyReLU(0.2) -> MaxPool 2
    Conv1d 16->32, kernel 11, "same" -> BatchNorm -> LeakyReLU(0.2) -> MaxPool 2      => 32 x D//4

then the branches' maps concatenated depth-wise (32·B channels, branch k's in channels 32(k-1)..32k-1)
-> flatten (channel-major) -> FC 172 -> LeakyReLU(0.2) -> Dropout 0.5 -> FC classes -> softmax (the
training loss applies it as cross-entropy). Max pooling floors odd lengths. The numbers are the
settings' defaults (channels, kernels, hidden, negative_slope, dropout, pool); n_features, n_classes
and branches (1..4) come from the run.

Two implementations compute it, from the same settings and, with the same seed, the same initial weights
(PyTorch's default init, drawn branch by branch, then the head):

* `PaperCNN1D` below, in plain torch.nn layers: read it to see the method (`model=cnn1d_reference`).
* `MultiBranchCNN1D` (meshseg/models/cnn1d_fast.py), faster kernels on a few CPU cores: what
  `model=cnn1d` trains. tests/test_cnn1d.py holds its logits, gradients and batch-norm statistics to
  `PaperCNN1D`'s, and tests/test_cnn1d_reference.py trains a fold with each.

Speed: benchmarks/train_throughput.py times both, interleaved, in one run. Its run recorded in docs/benchmarks.md
(2 threads, `--malloc-tune`, 2026-11-24) trained `MultiBranchCNN1D` at 1.26-1.54 times
the samples/s of `PaperCNN1D` for 1-4 branches; machines of this kind differ, so compare one run only.
"""

from __future__ import annotations

import torch
from torch import nn

from meshseg.models.cnn1d_fast import EVAL_CHUNK, MultiBranchCNN1D
from meshseg.models.settings import CNN1DSettings

__all__ = ["PaperCNN1D", "MultiBranchCNN1D", "CNN1DSettings", "flops_per_sample", "EVAL_CHUNK"]


class PaperCNN1D(nn.Module):
    """The network as the paper draws it: one nn.Sequential per branch, the branches' maps concatenated
    on the channel axis, then the fully connected head. Input (N, branches, n_features): branch k reads
    X^{k+1}; output logits (N, n_classes). `settings`: CNN1DSettings' fields, as conf/model/*.yaml gives them."""

    Settings = CNN1DSettings  # checked when the method is built (meshseg.training.fitters.NetFitter)

    def __init__(self, n_features: int, n_classes: int, branches: int = 3, **settings):
        super().__init__()
        s = self.settings = CNN1DSettings.of(settings)
        length = s.out_length(n_features, branches)

        def branch() -> nn.Sequential:
            layers, c_in = [], 1
            for c_out, k in zip(s.channels, s.kernels):
                layers += [
                    nn.Conv1d(c_in, c_out, k, padding="same"),
                    nn.BatchNorm1d(c_out),
                    nn.LeakyReLU(s.negative_slope),
                    nn.MaxPool1d(s.pool),
                ]
                c_in = c_out
            return nn.Sequential(*layers)

        self.branches = nn.ModuleList(branch() for _ in range(branches))
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(branches * s.channels[-1] * length, s.hidden),
            nn.LeakyReLU(s.negative_slope),
            nn.Dropout(s.dropout),
            nn.Linear(s.hidden, int(n_classes)),
        )

    def feature_maps(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([b(x[:, k : k + 1]) for k, b in enumerate(self.branches)], dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.feature_maps(x))


def flops_per_sample(n_features: int, n_classes: int, branches: int = 3, settings: CNN1DSettings | None = None) -> int:
    """Forward FLOPs of one sample: 2 x the multiply-adds of the convolutions and the two linear layers.

    Batch norm, activations, pooling and biases (a few operations per activation, not per weight) are
    not counted. A training step costs about 3x this per sample (forward, and backward for inputs and weights).
    """
    s = settings or CNN1DSettings()
    macs, length, c_in = 0, int(n_features), 1
    for c_out, k in zip(s.channels, s.kernels):
        macs += branches * length * c_out * c_in * k  # 'same' convolution: one output per input position
        length, c_in = length // s.pool, c_out
    macs += branches * c_in * length * s.hidden + s.hidden * n_classes
    return 2 * macs
