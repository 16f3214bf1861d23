"""The multi-branch 1D CNN (meshseg.models.cnn1d) against the paper's §3.4 and a straightforward reference.

The reference is `meshseg.models.cnn1d.PaperCNN1D`: nn.Conv1d / nn.BatchNorm1d / nn.LeakyReLU /
nn.MaxPool1d per branch, as the paper draws it; the fast network must compute exactly what it does.
"""

from __future__ import annotations

import re

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from meshseg.models.cnn1d import EVAL_CHUNK, MultiBranchCNN1D, PaperCNN1D, flops_per_sample

# the reference's nn.Conv1d(padding="same") warns about even kernels (one test config has one)
pytestmark = pytest.mark.filterwarnings("ignore:Using padding='same' with even kernel")


def _pairs(fast: MultiBranchCNN1D, ref: PaperCNN1D, grads: bool = False):
    """{name: (fast tensor, reference tensor)} in the documented mapping: every parameter and running
    statistic, or with grads=True every parameter's gradient."""
    get = (lambda t: t.grad) if grads else (lambda t: t)
    out = {}
    for k, branch in enumerate(ref.branches):
        convs = [m for m in branch if isinstance(m, nn.Conv1d)]
        bns = [m for m in branch if isinstance(m, nn.BatchNorm1d)]
        for i, (layer, conv, bn) in enumerate(zip(fast.layers, convs, bns, strict=True)):
            out |= {
                f"branch{k}.conv{i}.weight": (get(layer.weight)[k], get(conv.weight)),
                f"branch{k}.conv{i}.bias": (get(layer.bias)[k], get(conv.bias)),
                f"branch{k}.bn{i}.weight": (get(layer.bn_weight)[k], get(bn.weight)),
                f"branch{k}.bn{i}.bias": (get(layer.bn_bias)[k], get(bn.bias)),
            }
            if not grads:
                out |= {
                    f"branch{k}.bn{i}.running_mean": (layer.running_mean[k], bn.running_mean),
                    f"branch{k}.bn{i}.running_var": (layer.running_var[k], bn.running_var),
                }
    for name, mine, theirs in (("fc1", fast.fc1, ref.head[1]), ("fc2", fast.fc2, ref.head[4])):
        out |= {
            f"{name}.weight": (get(mine.weight), get(theirs.weight)),
            f"{name}.bias": (get(mine.bias), get(theirs.bias)),
        }
    return out


def copy_reference_into(fast: MultiBranchCNN1D, ref: PaperCNN1D) -> None:
    """Load the reference's parameters and running statistics into the fast model."""
    with torch.no_grad():
        for mine, theirs in _pairs(fast, ref).values():
            mine.copy_(theirs)


def assert_close(a: torch.Tensor, b: torch.Tensor, rel: float = 1e-4, scale: float | None = None, what: str = ""):
    """max |a - b| <= rel * scale, scale = max |b| unless given."""
    a, b = a.detach(), b.detach()
    scale = float(b.abs().max()) if scale is None else scale
    err = float((a - b).abs().max())
    assert err <= rel * scale, f"{what}: max abs diff {err:.3g} > {rel} x {scale:.3g}"


CONFIGS = [
    dict(n_features=800, n_classes=8, branches=3),  # the paper's network
    dict(n_features=603, n_classes=5, branches=2),  # odd lengths: 603 -> 301 -> 150
    dict(n_features=91, n_classes=4, branches=4, channels=(4, 6), kernels=(4, 5), hidden=10, pool=3),  # even kernel
]


@pytest.fixture(params=range(len(CONFIGS)), ids=["paper", "odd-lengths", "pool3-even-kernel"])
def pair(request):
    cfg = CONFIGS[request.param]
    torch.manual_seed(0)
    ref = PaperCNN1D(**cfg)
    fast = MultiBranchCNN1D(**cfg)
    copy_reference_into(fast, ref)
    x = torch.randn(12, cfg["branches"], cfg["n_features"]) * 2 + 0.5
    y = torch.randint(0, cfg["n_classes"], (12,))
    return fast, ref, x, y


@pytest.mark.parametrize("branches", [1, 2, 3, 4])
def test_layer_shapes(branches):
    net = MultiBranchCNN1D(800, 7, branches)
    x = torch.randn(5, branches, 800)
    assert net.feature_maps(x).shape == (5, 32 * branches, 200)  # each branch: 32 channels x 200 positions
    assert net(x).shape == (5, 7)
    net.eval()
    assert net(x).shape == (5, 7)
    assert [tuple(layer.weight.shape) for layer in net.layers] == [(branches, 16, 1, 15), (branches, 32, 16, 11)]
    assert net.fc1.in_features == 32 * branches * 200 and net.fc1.out_features == 172


def test_600_features_give_150_positions():
    net = MultiBranchCNN1D(600, 3, 3)
    assert net.feature_maps(torch.randn(2, 3, 600)).shape == (2, 96, 150)
    assert net.fc1.in_features == 96 * 150


@pytest.mark.parametrize("k", [0, 1, 2])
def test_branches_are_separate(k):
    """Changing X^k changes channels 32k..32k+31 of the concatenated map and nothing else."""
    torch.manual_seed(0)
    net = MultiBranchCNN1D(800, 5, 3).eval()
    x = torch.randn(4, 3, 800)
    x2 = x.clone()
    x2[:, k] += torch.randn(4, 800)
    with torch.no_grad():
        changed = (net.feature_maps(x) - net.feature_maps(x2)).abs().amax(dim=(0, 2)) > 0
    expected = torch.zeros(96, dtype=torch.bool)
    expected[32 * k : 32 * (k + 1)] = True
    assert torch.equal(changed, expected)


def test_branch_parameters_are_distinct():
    net = MultiBranchCNN1D(800, 5, 3)
    for layer in net.layers:
        w = layer.weight.detach()
        assert not torch.equal(w[0], w[1]) and not torch.equal(w[1], w[2])


def test_same_seed_same_init_as_reference():
    """Both draw PyTorch's default init in the same order, so one seed gives one network."""
    torch.manual_seed(3)
    ref = PaperCNN1D(800, 8, 3)
    torch.manual_seed(3)
    fast = MultiBranchCNN1D(800, 8, 3)
    for mine, theirs in _pairs(fast, ref).values():
        assert torch.equal(mine, theirs)


def test_forward_matches_reference_train_and_eval(pair):
    fast, ref, x, _ = pair
    for mode in (True, False):
        fast.train(mode), ref.train(mode)
        torch.manual_seed(1)  # the same dropout mask
        a = fast(x)
        torch.manual_seed(1)
        b = ref(x)
        assert_close(a, b)
        assert_close(fast.feature_maps(x), ref.feature_maps(x))


def test_gradients_and_running_stats_match_reference(pair):
    fast, ref, x, y = pair
    fast.train(), ref.train()
    opts = [torch.optim.SGD(m.parameters(), lr=0.1, momentum=0.9) for m in (fast, ref)]
    for model in (fast, ref):
        torch.manual_seed(1)
        F.cross_entropy(model(x), y).backward()
    grads = _pairs(fast, ref, grads=True)
    for name, (g_fast, g_ref) in grads.items():
        # a conv bias feeding batch norm has zero gradient in train mode (BN removes any constant): both are
        # rounding noise, so they are compared on the scale of the same layer's weight gradient
        conv_bias = ".conv" in name and name.endswith("bias")
        scale = float(grads[name.replace("bias", "weight")][1].abs().max()) if conv_bias else None
        assert_close(g_fast, g_ref, scale=scale, what=name)
    for opt in opts:
        opt.step()
    for name, (mine, theirs) in _pairs(fast, ref).items():  # parameters after the step, updated running stats
        assert_close(mine, theirs, what=name)
    fast.eval(), ref.eval()
    assert_close(fast(x), ref(x))


def test_eval_mode_gradients_match_reference(pair):
    """In eval mode batch norm is a fixed affine map, so the conv bias gradients are not zero: check them all,
    and the gradient with respect to the input."""
    fast, ref, x, y = pair
    fast.eval(), ref.eval()
    xs = [x.clone().requires_grad_() for _ in range(2)]
    for model, xi in zip((fast, ref), xs):
        F.cross_entropy(model(xi), y).backward()
    assert_close(xs[0].grad, xs[1].grad, what="input")
    for name, (g_fast, g_ref) in _pairs(fast, ref, grads=True).items():
        assert_close(g_fast, g_ref, what=name)


def test_eval_no_grad_in_chunks_matches_reference():
    """A no-grad eval forward on CPU runs in chunks of EVAL_CHUNK samples: the same logits as one batch."""
    torch.manual_seed(0)
    ref = PaperCNN1D(800, 6, 3)
    fast = MultiBranchCNN1D(800, 6, 3)
    copy_reference_into(fast, ref)
    x_train = torch.randn(64, 3, 800) * 3 + 1
    for model in (fast, ref):  # non-trivial running statistics
        model.train()(x_train)
        model.eval()
    x = torch.randn(EVAL_CHUNK * 2 + 5, 3, 800)
    with torch.no_grad():
        assert_close(fast(x), ref(x))


def test_invalid_arguments():
    with pytest.raises(ValueError, match=r"1\.\.4"):
        MultiBranchCNN1D(800, 8, branches=5)
    with pytest.raises(ValueError, match=r"1\.\.4"):
        MultiBranchCNN1D(800, 8, branches=0)
    net = MultiBranchCNN1D(800, 8, 3)
    for shape in [(4, 2, 800), (4, 3, 799), (4, 2400), (3, 800)]:
        with pytest.raises(ValueError, match=re.escape("expected input of shape (N, 3, 800)")) as err:
            net(torch.randn(*shape))
        assert f"got {shape}" in str(err.value)


def test_flops_per_sample_hand_count():
    # B=3, D=800, 8 classes, multiply-adds:
    #   conv1: 3 branches x 800 positions x 16 out x 1 in x 15 taps  =    576,000
    #   conv2: 3 x 400 x 32 out x 16 in x 11 taps                    =  6,758,400
    #   fc1:   (3 x 32 x 200 = 19,200 inputs) x 172                  =  3,302,400
    #   fc2:   172 x 8                                               =      1,376
    #   total 10,638,176 MACs = 21,276,352 FLOPs
    assert flops_per_sample(800, 8, 3) == 21_276_352
    assert flops_per_sample(600, 8, 1) == 2 * (600 * 16 * 15 + 300 * 32 * 16 * 11 + 32 * 150 * 172 + 172 * 8)


def test_same_seed_same_outputs():
    x = torch.randn(6, 3, 800)
    outs = []
    for _ in range(2):
        torch.manual_seed(7)
        net = MultiBranchCNN1D(800, 8, 3)
        outs.append(net(x))  # train mode: dropout from the same seed
        outs.append(net.eval()(x))
    assert torch.equal(outs[0], outs[2]) and torch.equal(outs[1], outs[3])
