"""trainer.precision=bf16-mixed: the fast 1D CNN under CPU autocast against the reference network, a real
training in bf16-mixed, prediction in float32, and the refusal of bf16 where the CPU has no bf16 arithmetic.

The numeric tests need no bf16 hardware: without AVX512_BF16/AMX PyTorch computes the same bf16 roundings
in its reference kernels, only slower. So they run on every CPU, also where meshseg refuses bf16 for speed.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf
from test_cnn1d import _pairs, copy_reference_into
from test_run import compose_run

from meshseg.errors import ConfigError
from meshseg.models.cnn1d import EVAL_CHUNK, MultiBranchCNN1D, PaperCNN1D
from meshseg.training import context
from meshseg.training.context import TrainContext
from meshseg.training.data import Standardiser, TrainSet
from meshseg.training.loop import train_stage, transform
from meshseg.training.module import Segmenter

# Tolerances, as norm-wise relative errors ||a - b|| / ||fp32|| (bf16 keeps 8 significant bits, so each
# rounding is off by up to u = 2^-9 ~ 0.002 of the value). Measured on an AVX2 CPU over 6 seeds, branches 1
# and 3, batch 32 x 800 features:
# * logits: each bf16 path within 0.0069 of fp32 (a few roundings of u), the two within 0.0022 of each other
#   (they round the same tensors). Allowed: 0.02 and 0.01.
# * gradients: each bf16 path within 0.20 of fp32 (the first batch norm's bias; 0.06-0.12 elsewhere, except fc2
#   at 0.007). Not arithmetic drift: batch norm's backward subtracts means over N x L positions that nearly
#   cancel, and where bf16 rounding flips a LeakyReLU sign or a max-pool winner, a whole row of the gradient
#   changes. The two bf16 paths share most roundings: within 0.053 of each other. Allowed: 0.1 between the
#   two, and the fast network no further from fp32 than 1.25 x the reference's distance + 0.02.
LOGITS_VS_FP32, LOGITS_BETWEEN = 0.02, 0.01
GRADS_BETWEEN, GRADS_VS_REFERENCE, GRADS_SLACK = 0.1, 1.25, 0.02


def rel(a: torch.Tensor, b: torch.Tensor, scale: torch.Tensor) -> float:
    return float((a.double() - b.double()).norm() / scale.double().norm())


def logits_and_grads(model, fast, ref, x, y, bf16: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """One forward (dropout mask from seed 1) and cross-entropy backward of `model`, in bf16-mixed as Lightning
    runs it (autocast around the forward and the loss, backward outside): logits and every parameter's gradient
    by the names of test_cnn1d's mapping."""
    model.zero_grad(set_to_none=False)
    torch.manual_seed(1)
    with torch.autocast("cpu", torch.bfloat16, enabled=bf16):
        logits = model(x)
        loss = F.cross_entropy(logits, y)
    loss.backward()
    side = 0 if model is fast else 1
    return logits.detach().float(), {k: v[side].clone() for k, v in _pairs(fast, ref, grads=True).items()}


@pytest.mark.parametrize("branches", [1, 3])
def test_bf16_fast_network_matches_reference(branches):
    torch.manual_seed(0)
    ref = PaperCNN1D(800, 8, branches)
    fast = MultiBranchCNN1D(800, 8, branches)
    copy_reference_into(fast, ref)
    for p in [*fast.parameters(), *ref.parameters()]:
        p.grad = torch.zeros_like(p)
    x = torch.randn(32, branches, 800) * 2 + 0.5
    y = torch.randint(0, 8, (32,))
    fp32 = logits_and_grads(ref, fast, ref, x, y, bf16=False)
    fast16 = logits_and_grads(fast, fast, ref, x, y, bf16=True)
    ref16 = logits_and_grads(ref, fast, ref, x, y, bf16=True)

    assert rel(fast16[0], fp32[0], fp32[0]) <= LOGITS_VS_FP32
    assert rel(ref16[0], fp32[0], fp32[0]) <= LOGITS_VS_FP32
    assert rel(fast16[0], ref16[0], fp32[0]) <= LOGITS_BETWEEN
    for name, g32 in fp32[1].items():
        # a conv bias feeding batch norm has zero gradient in train mode: compared on its weight gradient's scale
        scale = fp32[1][name.replace("bias", "weight")] if ".conv" in name and name.endswith("bias") else g32
        between = rel(fast16[1][name], ref16[1][name], scale)
        fast_err, ref_err = rel(fast16[1][name], g32, scale), rel(ref16[1][name], g32, scale)
        assert between <= GRADS_BETWEEN, f"{name}: bf16 fast vs reference {between:.3g}"
        assert fast_err <= GRADS_VS_REFERENCE * ref_err + GRADS_SLACK, f"{name}: {fast_err:.3g} vs {ref_err:.3g}"
        assert all(g.dtype == torch.float32 for g in (fast16[1][name], ref16[1][name]))  # fp32 master weights


def test_bf16_eval_forward_matches_reference():
    """Eval mode folds batch norm into the convolution, which then rounds the folded weights to bf16."""
    torch.manual_seed(0)
    ref = PaperCNN1D(800, 8, 3)
    fast = MultiBranchCNN1D(800, 8, 3)
    copy_reference_into(fast, ref)
    for model in (fast, ref):  # non-trivial running statistics
        model.train()(torch.randn(64, 3, 800) * 3 + 1)
        model.eval()
    x = torch.randn(EVAL_CHUNK + 8, 3, 800)  # more than one chunk
    with torch.no_grad():
        fp32 = ref(x)
        with torch.autocast("cpu", torch.bfloat16):
            fast16, ref16 = fast(x).float(), ref(x).float()
    assert rel(fast16, fp32, fp32) <= LOGITS_VS_FP32 and rel(ref16, fp32, fp32) <= LOGITS_VS_FP32
    assert rel(fast16, ref16, fp32) <= 2 * LOGITS_BETWEEN  # the folded weights add one rounding


class Recording(Segmenter):
    """Segmenter that keeps each training step's loss and logits dtype."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.losses, self.dtypes = [], set()

    def training_step(self, batch, batch_idx):
        x, y = batch
        logits = self.net(x)
        self.dtypes.add(logits.dtype)
        loss = F.cross_entropy(logits, y)
        self.losses.append(float(loss.detach()))
        return loss


def test_bf16_mixed_training_runs_and_learns():
    """A real Lightning fit in bf16-mixed (what crashed in convolution_backward before): 384 samples, 2 epochs."""
    rng = np.random.default_rng(0)
    X = rng.standard_normal((384, 2, 64)).astype(np.float32)
    y = (X[:, 0, :32].mean(1) > X[:, 1, 32:].mean(1)).astype(np.int64) + 2 * (X[:, 0, 32:].mean(1) > 0)
    X[np.arange(384), 1, y] += 2.0  # an easy, learnable signal besides the harder one
    torch.manual_seed(0)
    module = Recording(MultiBranchCNN1D(64, 4, 2), 2, lr_start=0.02, lr_end=0.02)
    train_stage(module, TrainSet(X, y, Standardiser().fit(X), 384, 4), TrainContext(2, 32, precision="bf16-mixed"))
    assert module.dtypes == {torch.bfloat16}  # the step ran under autocast
    assert all(p.dtype == torch.float32 for p in module.parameters())
    steps = len(module.losses) // 2
    first, last = np.mean(module.losses[:steps]), np.mean(module.losses[steps:])
    assert last < 0.8 * first, module.losses
    assert np.isfinite(module.losses).all()

    # prediction runs in float32, also when called inside an autocast region
    proba, logits = module.predict_proba(X), transform(module.net, X, 100, torch.device("cpu"))
    with torch.autocast("cpu", torch.bfloat16):
        assert np.array_equal(module.predict_proba(X), proba)
        assert np.array_equal(transform(module.net, X, 100, torch.device("cpu")), logits)
    assert proba.dtype == logits.dtype == np.float32


# --- the precision check -------------------------------------------------------------------------------


def trainer_cfg(precision, accelerator="cpu"):
    return OmegaConf.create(
        {
            "accelerator": accelerator,
            "devices": 1,
            "precision": precision,
            "threads": 1,
            "predict_batch_size": 256,
            "progress_bar": False,
        }
    )


BUDGET = OmegaConf.create({"epochs": 2, "batch_size": 32})


def test_bf16_is_refused_on_a_cpu_without_bf16(monkeypatch):
    monkeypatch.setattr(context, "cpu_bf16_flags", lambda: [])
    with pytest.raises(ConfigError) as err:
        TrainContext.from_config(BUDGET, trainer_cfg("bf16-mixed"), 0)
    message = str(err.value)
    assert message.startswith("trainer.precision=bf16-mixed is not allowed on this CPU: it lacks AVX512_BF16/AMX (")
    assert "\n" not in message
    # a GPU run is not the CPU's business
    assert TrainContext.from_config(BUDGET, trainer_cfg("bf16-mixed", "gpu"), 0).precision == "bf16-mixed"


def test_bf16_is_allowed_on_a_cpu_with_bf16(monkeypatch):
    monkeypatch.setattr(context, "cpu_bf16_flags", lambda: ["amx_bf16"])
    assert TrainContext.from_config(BUDGET, trainer_cfg("bf16-mixed"), 0).precision == "bf16-mixed"


@pytest.mark.parametrize("precision", ["16-mixed", "bf16-true", "64-true", "fp16", 16, "bf16"])
def test_other_precisions_are_refused_on_the_cpu(precision, monkeypatch):
    monkeypatch.setattr(context, "cpu_bf16_flags", lambda: ["avx512_bf16"])
    with pytest.raises(ConfigError) as err:
        TrainContext.from_config(BUDGET, trainer_cfg(precision), 0)
    assert str(err.value) == (
        f"trainer.precision={precision} is not allowed with trainer.accelerator=cpu: "
        "choose one of ['32-true', 'bf16-mixed']"
    )


@pytest.mark.parametrize("precision", ["32-true", "32", 32])
def test_32_true_and_its_aliases(precision):
    assert TrainContext.from_config(BUDGET, trainer_cfg(precision), 0).precision == "32-true"


def test_a_run_refuses_bf16_before_any_work(tmp_path, monkeypatch):
    from meshseg.run import run

    monkeypatch.setattr(context, "cpu_bf16_flags", lambda: [])
    cfg = compose_run(
        "trainer.precision=bf16-mixed",
        f"paths.mlflow_dir={tmp_path}/mlruns",
        f"paths.cache_dir={tmp_path}/cache",
        f"paths.log_dir={tmp_path}/logs",
    )
    with pytest.raises(ConfigError, match=r"^trainer\.precision=bf16-mixed is not allowed on this CPU"):
        run(cfg)
    assert list(tmp_path.iterdir()) == []  # no store, no features


def test_cpu_bf16_flags_from_cpuinfo(tmp_path):
    cpuinfo = tmp_path / "cpuinfo"
    for text, expected in [
        ("processor\t: 0\nflags\t\t: fpu sse avx2 avx512f\n", []),  # AVX-512 without bf16
        ("flags\t\t: avx2 avx512f avx512_bf16 amx_bf16 amx_tile\n", ["avx512_bf16", "amx_bf16"]),
        ("Features\t: fp asimd bf16 sve\n", ["bf16"]),  # aarch64
    ]:
        cpuinfo.write_text(text)
        assert context.cpu_bf16_flags(cpuinfo) == expected
    assert context.cpu_bf16_flags(tmp_path / "missing") == []
