"""The ToG15 baseline (Guo, Zou & Chen, "3D Mesh Labeling via Deep Convolutional Neural Networks",
ACM ToG 35(1), 2015): each face's feature vector reshaped into a small image and classified by a 2D CNN.

What is known, and from where:

* ToG15 §3.1: seven feature families (curvature, PCA, SDF, distance from medial surface, AGD, shape
  context, spin images), 600 components, "reorganised" into a 30 x 20 feature matrix; the ordering of
  the features and the size of the matrix "only slightly change" the accuracy.
* George et al. 2018, figure 2: the 30 x 20 image with the families in contiguous rows from top to
  bottom (the vector laid out row by row), and "7x5 convolutional filters" passed over it.

The layer list itself (channels, the other kernels, pooling, the fully connected part, activations,
training settings) is not in either text at hand, so every one of those is a setting (`CNN2DSettings`)
and a value in conf/model/cnn2d.yaml, listed in docs/deviations.md. The default is a LeNet-style network of
its time:

    input (N, 1, D) -> image (N, 1, H, W), H x W = D, row-major: feature j at (j // W, j % W)
    Conv2d 1->16, kernel 7x5 (H x W), "same" -> BatchNorm -> ReLU -> MaxPool 2x2      30x20 -> 15x10
    Conv2d 16->32, kernel 5x5, "same"        -> BatchNorm -> ReLU -> MaxPool 2x2      15x10 -> 7x5
    flatten (channel-major, as nn.Flatten) -> Linear(32*7*5 -> 128) -> ReLU -> Dropout 0.5
    -> Linear(128 -> classes): logits (the caller applies cross-entropy)

Batch norm is on by default although neither text at hand mentions it: without it, SGD with the 1D CNN's
learning-rate schedule under-fits in short budgets (synthetic figures, demo budget: training accuracy
0.67, test 0.77; with it 0.93 / 0.96; both reach 0.98 in the cpu budget), and the paper's 1D CNN has it,
so the comparison is about the 2D reshape rather than the optimiser. `batch_norm=False` drops it.
Max pooling floors odd sizes, like nn.MaxPool2d. Initialisation is PyTorch's default.

Speed on CPU: the maps are kept channels-last (NHWC), which oneDNN convolves, pools and normalises
faster than NCHW for these small images (1 core: about 1.3x the training and 2.3x the prediction
speed); a no-grad eval forward runs in cache-sized chunks, as the 1D CNN does. benchmarks/
cnn2d_throughput.py measures the result beside the 1D CNN.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from meshseg.errors import ConfigError
from meshseg.models.settings import CNN2DSettings

EVAL_CHUNK = 128  # samples per chunk of a no-grad eval-mode forward on CPU


class ToG15CNN2D(nn.Module):
    """ToG15's 2D CNN: input (N, 1, n_features) float -> logits (N, n_classes). `settings`:
    CNN2DSettings' fields (meshseg/models/settings.py), as conf/model/cnn2d.yaml gives them.

    `branches` must be 1 (ToG15 reads one feature vector per face); it is an argument so that the
    training code can build every model the same way.
    """

    Settings = CNN2DSettings  # checked when the method is built (meshseg.training.fitters.NetFitter)

    def __init__(self, n_features: int, n_classes: int, branches: int = 1, **settings):
        super().__init__()
        s = self.settings = CNN2DSettings.of(settings)
        height, width = s.image_shape
        if branches != 1:
            raise ConfigError(f"branches={branches} is not allowed: ToG15CNN2D takes branches=1 (one vector per face)")
        if height * width != n_features:
            raise s.refuse(
                "image_shape",
                f"it holds {height * width} values, but there are {n_features} features: choose H x W = {n_features}",
            )
        self.n_features, self.n_classes, self.branches = int(n_features), int(n_classes), 1
        self.image_shape = (height, width)
        self.activation, self.negative_slope, self.dropout = s.activation, s.negative_slope, s.dropout
        self.pool = s.pool
        self.convs = nn.ModuleList()
        self.norms = nn.ModuleList()
        c_in = 1
        for c_out, (kh, kw) in zip(s.channels, s.kernels):
            same = s.padding == "same"
            self.convs.append(nn.Conv2d(c_in, c_out, (kh, kw), padding=(kh // 2, kw // 2) if same else 0))
            self.norms.append(nn.BatchNorm2d(c_out) if s.batch_norm else nn.Identity())
            c_in = c_out
        self.out_shape = (c_in, *s.map_shape())  # the map before flattening
        self.fc1 = nn.Linear(c_in * self.out_shape[1] * self.out_shape[2], s.hidden)
        self.fc2 = nn.Linear(s.hidden, self.n_classes)
        self.to(memory_format=torch.channels_last)  # conv weights NHWC too: oneDNN then skips reorders

    def image(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 1, D) -> (N, 1, H, W): row r of the image holds features r·W .. r·W + W - 1."""
        return self._check(x).reshape(len(x), 1, *self.image_shape)

    def feature_maps(self, x: torch.Tensor) -> torch.Tensor:
        """The last pooled map (N, C, h, w), before flattening (train mode updates batch-norm statistics)."""
        h = self.image(x).contiguous(memory_format=torch.channels_last)
        for conv, norm in zip(self.convs, self.norms):
            h = self._act(norm(conv(h)))
            if self.pool > 1:
                h = F.max_pool2d(h, self.pool)
        return h

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.device.type == "cpu" and not self.training and not torch.is_grad_enabled() and len(x) > EVAL_CHUNK:
            # samples are independent in eval mode, and cache-sized chunks run faster on CPU
            return torch.cat([self._logits(chunk) for chunk in x.split(EVAL_CHUNK)])
        return self._logits(x)

    def _logits(self, x: torch.Tensor) -> torch.Tensor:
        h = self._act(self.fc1(self.feature_maps(x).flatten(1)))
        return self.fc2(F.dropout(h, self.dropout, self.training))

    def _act(self, h: torch.Tensor) -> torch.Tensor:
        if self.activation == "relu":
            return F.relu(h)
        if self.activation == "leaky_relu":
            return F.leaky_relu(h, self.negative_slope)
        return torch.tanh(h) if self.activation == "tanh" else torch.sigmoid(h)

    def _check(self, x: torch.Tensor) -> torch.Tensor:
        if x.dim() != 3 or tuple(x.shape[1:]) != (1, self.n_features):
            raise ValueError(
                f"expected input of shape (N, 1, {self.n_features}) (batch, branches, features), got {tuple(x.shape)}"
            )
        return x.to(self.fc1.weight.dtype)
