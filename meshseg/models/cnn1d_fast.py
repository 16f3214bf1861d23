"""`MultiBranchCNN1D`: the paper's multi-branch 1D CNN (architecture and settings: meshseg/models/cnn1d.py)
computed by kernels written for training speed on a few CPU cores. It computes what `PaperCNN1D` computes
(logits, gradients, batch-norm statistics; tests/test_cnn1d.py), by

* keeping every feature map channels-last, (N, L, C) in memory, and running each convolution as a
  ``conv2d`` on an (N, C, 1, L) channels-last view: oneDNN runs that at over half the matmul peak, and
  batch norm and pooling on channels-last maps are several times faster than on channels-first ones;
* asking oneDNN's backward only for the gradients needed (never the input's of the first layer) and
  summing the bias gradient separately, which oneDNN computes slowly for these shapes;
* pooling before the LeakyReLU (it is monotonic, so the max commutes with it: half the activation work)
  in one autograd Function that keeps a 0/1 "first of the pair won" mask instead of int64 indices.

Under torch.autocast (Lightning's ``precision="bf16-mixed"``) each convolution casts its operands to the
autocast dtype itself, so that its backward sees the tensors the convolution read; the result equals
`PaperCNN1D` under autocast to bf16 rounding (tests/test_bf16.py). Without autocast nothing changes.

Batch norm in train mode is PyTorch's own (``F.batch_norm`` on the channels-last view: normalises with
the batch statistics, updates the running ones with momentum 0.1, eps 1e-5), so it behaves exactly as
``nn.BatchNorm1d``. In eval mode it is the affine map of the running statistics, folded into the
convolution's weight and bias; and a no-grad eval forward on CPU runs in chunks of 128 samples (the
samples are independent then), about twice as fast as one large batch.

Parameters are stacked over branches: entry [k] of each is what branch k+1's ``nn.Conv1d`` and
``nn.BatchNorm1d`` hold in `PaperCNN1D` (``layers[i]`` is the i-th conv stage):

    layers[i].weight        (B, C_out, C_in, K)   <- Conv1d.weight  (same shape)
    layers[i].bias          (B, C_out)            <- Conv1d.bias
    layers[i].bn_weight     (B, C_out)            <- BatchNorm1d.weight
    layers[i].bn_bias       (B, C_out)            <- BatchNorm1d.bias
    layers[i].running_mean  (B, C_out)  buffer    <- BatchNorm1d.running_mean
    layers[i].running_var   (B, C_out)  buffer    <- BatchNorm1d.running_var
    fc1, fc2                nn.Linear             <- the head's two nn.Linear: fc1 reads the concatenated
                                                     map flattened channel-major, as nn.Flatten does

Initialisation is PyTorch's default (kaiming-uniform a=sqrt(5) and the matching uniform bias for the
convolutions and linear layers; BN weight 1, bias 0), drawn in `PaperCNN1D`'s order: branch by branch
(conv1, conv2), then fc1, fc2. With the same seed the two start identical.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from meshseg.models.settings import CNN1DSettings

EVAL_CHUNK = 128  # samples per chunk of a no-grad eval-mode forward on CPU


class _Conv(torch.autograd.Function):
    """F.conv2d (stride 1) whose backward computes only the gradients needed, the bias one by a plain sum."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, padding: tuple[int, int]):
        ctx.dtypes = x.dtype, weight.dtype, bias.dtype
        if torch.is_autocast_enabled(x.device.type):
            # Autocast would cast F.conv2d's operands only inside the call, so the backward would pair a bf16
            # gradient with the fp32 tensors saved here, which convolution_backward refuses (oneDNN: "could not
            # create a primitive descriptor"). Cast here instead and save what the convolution really read.
            dtype = torch.get_autocast_dtype(x.device.type)
            x, weight, bias = x.to(dtype), weight.to(dtype), bias.to(dtype)
        ctx.save_for_backward(x, weight)
        ctx.padding = list(padding)
        return F.conv2d(x, weight, bias, padding=padding)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        x, weight = ctx.saved_tensors
        need_x, need_w, need_b = ctx.needs_input_grad[:3]
        grad_x = grad_w = grad_b = None
        if need_x or need_w:
            grad_x, grad_w, _ = torch.ops.aten.convolution_backward(
                grad, x, weight, None, [1, 1], ctx.padding, [1, 1], False, [0, 0], 1, [need_x, need_w, False]
            )
        if need_b:
            grad_b = grad.permute(0, 2, 3, 1).reshape(-1, grad.shape[1]).sum(0)  # a view when channels-last
        # under autocast each gradient goes back in its input's own dtype (fp32 parameters); no-ops otherwise
        dx, dw, db = ctx.dtypes
        return _to(grad_x, dx), _to(grad_w, dw), _to(grad_b, db), None


def _to(t: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor | None:
    return None if t is None else t.to(dtype)


class _MaxPool2LeakyReLU(torch.autograd.Function):
    """LeakyReLU(max-pool by 2 over L) of an (N, L, C) map; an odd L drops the last position.

    Equals nn.MaxPool1d(2)(nn.LeakyReLU(slope)(z)) for slope >= 0, gradients included: a tie sends the
    gradient to the first of the pair, as PyTorch's max pooling does.
    """

    @staticmethod
    def forward(ctx, z: torch.Tensor, slope: float) -> torch.Tensor:
        length = z.shape[1]
        pairs = z[:, : length // 2 * 2].unflatten(1, (length // 2, 2))
        first, second = pairs[:, :, 0], pairs[:, :, 1]
        first_won = torch.ge(first, second, out=z.new_empty(first.shape))  # 1.0/0.0: float is faster than bool
        out = F.leaky_relu_(torch.maximum(first, second), slope)
        ctx.save_for_backward(first_won, out)
        ctx.slope, ctx.length = slope, length
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        first_won, out = ctx.saved_tensors
        n, half, c = out.shape
        # the gradient arrives transposed from the channel-major concatenation: one copy makes the rest fast
        grad = torch.ops.aten.leaky_relu_backward(grad.contiguous(), out, ctx.slope, True)
        grad_z = out.new_empty(n, ctx.length, c)
        pairs = grad_z[:, : 2 * half].unflatten(1, (half, 2))
        torch.mul(grad, first_won, out=pairs[:, :, 0])
        torch.sub(grad, pairs[:, :, 0], out=pairs[:, :, 1])
        if ctx.length % 2:
            grad_z[:, -1].zero_()
        return grad_z, None


def _pool_leaky_relu(z: torch.Tensor, pool: int, slope: float) -> torch.Tensor:
    """(N, L, C) -> (N, L // pool, C): max pool, then LeakyReLU (the same as LeakyReLU, then max pool)."""
    if pool == 2:
        if torch.is_grad_enabled() and z.requires_grad:
            return _MaxPool2LeakyReLU.apply(z, slope)
        pairs = z[:, : z.shape[1] // 2 * 2].unflatten(1, (-1, 2))
        return F.leaky_relu_(torch.maximum(pairs[:, :, 0], pairs[:, :, 1]), slope)
    pooled = F.max_pool2d(z.unsqueeze(1).permute(0, 3, 1, 2), (1, pool))  # on the (N, C, 1, L) channels-last view
    return F.leaky_relu(pooled, slope).permute(0, 2, 3, 1).flatten(1, 2)


class BranchConvBlock(nn.Module):
    """One Conv1d ('same') -> BatchNorm -> LeakyReLU -> MaxPool stage of all B branches, parameters stacked
    over branches; ``block(h, k)`` runs branch k on its (N, L, C_in) channels-last map."""

    def __init__(
        self, branches: int, in_channels: int, out_channels: int, kernel: int, pool: int, negative_slope: float
    ):
        super().__init__()
        self.kernel, self.pool, self.negative_slope = kernel, pool, negative_slope
        self.weight = nn.Parameter(torch.empty(branches, out_channels, in_channels, kernel))
        self.bias = nn.Parameter(torch.empty(branches, out_channels))
        self.bn_weight = nn.Parameter(torch.ones(branches, out_channels))
        self.bn_bias = nn.Parameter(torch.zeros(branches, out_channels))
        self.register_buffer("running_mean", torch.zeros(branches, out_channels))
        self.register_buffer("running_var", torch.ones(branches, out_channels))

    def reset_branch(self, k: int) -> None:
        """nn.Conv1d's default init of branch k's convolution."""
        with torch.no_grad():
            nn.init.kaiming_uniform_(self.weight[k], a=math.sqrt(5))
            bound = 1 / math.sqrt(self.weight[k][0].numel())  # 1 / sqrt(fan_in), fan_in = C_in * K
            nn.init.uniform_(self.bias[k], -bound, bound)

    def forward(self, h: torch.Tensor, k: int) -> torch.Tensor:
        """(N, L, C_in) -> (N, L // pool, C_out) for branch k; in train mode updates branch k's running stats."""
        if self.kernel % 2 == 0:  # 'same' with an even kernel pads one more on the right, as nn.Conv1d does
            h = F.pad(h, (0, 0, (self.kernel - 1) // 2, self.kernel // 2))
        x4 = h.unsqueeze(1).permute(0, 3, 1, 2)  # (N, C_in, 1, L) view with channels-last strides
        weight, bias, padding = self.weight[k], self.bias[k], (0, self.kernel // 2 if self.kernel % 2 else 0)
        if self.training:
            w4 = weight.unsqueeze(2).contiguous(memory_format=torch.channels_last)  # (C_out, C_in, 1, K)
            z4 = F.batch_norm(
                _Conv.apply(x4, w4, bias, padding),
                self.running_mean[k],
                self.running_var[k],
                self.bn_weight[k],
                self.bn_bias[k],
                True,
                0.1,
                1e-5,
            )  # (N, C_out, 1, L)
        else:  # batch norm with the running statistics is affine: fold it into the convolution
            scale = self.bn_weight[k] * (self.running_var[k] + 1e-5).rsqrt()
            w4 = (weight * scale[:, None, None]).unsqueeze(2).contiguous(memory_format=torch.channels_last)
            z4 = _Conv.apply(x4, w4, (bias - self.running_mean[k]) * scale + self.bn_bias[k], padding)
        return _pool_leaky_relu(z4.permute(0, 2, 3, 1).flatten(1, 2), self.pool, self.negative_slope)


class MultiBranchCNN1D(nn.Module):
    """The paper's multi-branch 1D CNN: input (N, branches, n_features) float -> logits (N, n_classes).
    `settings`: CNN1DSettings' fields, as conf/model/*.yaml gives them."""

    Settings = CNN1DSettings  # checked when the method is built (meshseg.training.fitters.NetFitter)

    def __init__(self, n_features: int, n_classes: int, branches: int = 3, **settings):
        super().__init__()
        s = self.settings = CNN1DSettings.of(settings)
        self.out_length = s.out_length(n_features, branches)
        self.n_features, self.n_classes, self.branches = int(n_features), int(n_classes), int(branches)
        self.dropout, self.negative_slope = s.dropout, s.negative_slope
        self.layers = nn.ModuleList(
            BranchConvBlock(branches, c_in, c_out, k, s.pool, s.negative_slope)
            for c_in, c_out, k in zip((1,) + s.channels[:-1], s.channels, s.kernels)
        )
        for k in range(branches):  # PaperCNN1D's init order: branch by branch, then the head
            for layer in self.layers:
                layer.reset_branch(k)
        self.fc1 = nn.Linear(branches * s.channels[-1] * self.out_length, s.hidden)
        self.fc2 = nn.Linear(s.hidden, self.n_classes)

    def feature_maps(self, x: torch.Tensor) -> torch.Tensor:
        """The depth-concatenated map before flattening: (N, channels[-1]·branches, n_features // pool**layers).

        Channels channels[-1]·k .. channels[-1]·(k+1) - 1 come from input branch k (0-based) alone.
        In train mode this updates the running statistics, as the forward pass does.
        """
        return self._feature_maps(self._check(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self._check(x)
        if x.device.type == "cpu" and not self.training and not torch.is_grad_enabled() and len(x) > EVAL_CHUNK:
            # samples are independent in eval mode, and cache-sized chunks run about twice as fast on CPU
            return torch.cat([self._logits(chunk) for chunk in x.split(EVAL_CHUNK)])
        return self._logits(x)

    def _check(self, x: torch.Tensor) -> torch.Tensor:
        expected = (self.branches, self.n_features)
        if x.dim() != 3 or tuple(x.shape[1:]) != expected:
            raise ValueError(
                f"expected input of shape (N, {expected[0]}, {expected[1]}) "
                f"(batch, branches, features), got {tuple(x.shape)}"
            )
        return x.to(self.fc1.weight.dtype)

    def _feature_maps(self, x: torch.Tensor) -> torch.Tensor:
        maps = []
        for k in range(self.branches):
            h = x[:, k].unsqueeze(2)  # (N, D, 1): a channels-last map with one channel
            for layer in self.layers:
                h = layer(h, k)
            maps.append(h.transpose(1, 2))  # (N, C, L) view: the concatenation writes it channel-major
        return torch.cat(maps, dim=1)

    def _logits(self, x: torch.Tensor) -> torch.Tensor:
        h = F.leaky_relu_(self.fc1(self._feature_maps(x).flatten(1)), self.negative_slope)
        return self.fc2(F.dropout(h, self.dropout, self.training))
