"""The ToG15 2D CNN baseline (meshseg.models.cnn2d, conf/model/cnn2d.yaml): shapes, the row-major
reshape, argument checks, determinism, and `model=cnn2d` through the real CLI."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
import torch
import torch.nn.functional as F
from conftest import REPO
from hydra import compose, initialize_config_dir
from mlflow import MlflowClient
from torch import nn

from meshseg import CONF_DIR
from meshseg.errors import ConfigError
from meshseg.models.cnn2d import EVAL_CHUNK, ToG15CNN2D


def compose_run(*overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("run", overrides=list(overrides))


# --- the network -----------------------------------------------------------------------------------


def test_default_shapes():
    net = ToG15CNN2D(600, 5)
    x = torch.randn(7, 1, 600)
    assert net.image(x).shape == (7, 1, 30, 20)
    assert net.feature_maps(x).shape == (7, 32, 7, 5)  # 30x20 -> pool 15x10 -> pool 7x5 (floored)
    assert net.out_shape == (32, 7, 5) and net.fc1.in_features == 32 * 7 * 5 and net.fc1.out_features == 128
    assert [tuple(c.weight.shape) for c in net.convs] == [(16, 1, 7, 5), (32, 16, 5, 5)]  # kernels are H x W
    assert net(x).shape == (7, 5)
    assert net.eval()(x).shape == (7, 5)


def test_valid_padding_and_other_shapes():
    # 30x20 -valid 7x5-> 24x16 -pool-> 12x8 -valid 5x5-> 8x4 -pool-> 4x2
    net = ToG15CNN2D(600, 3, padding="valid", batch_norm=False)
    assert net.feature_maps(torch.randn(2, 1, 600)).shape == (2, 32, 4, 2)
    # 800 features as a 40x20 image, three layers of square 3x3 kernels: 40x20 -> 20x10 -> 10x5 -> 5x2
    net = ToG15CNN2D(800, 4, image_shape=(40, 20), channels=(4, 8, 6), kernels=(3, 3, 3), hidden=9)
    assert net.feature_maps(torch.randn(2, 1, 800)).shape == (2, 6, 5, 2)
    assert net.fc1.in_features == 6 * 5 * 2 and net(torch.randn(2, 1, 800)).shape == (2, 4)


@pytest.mark.parametrize("j", [0, 19, 20, 137, 599])
def test_feature_j_lands_at_row_j_div_w_column_j_mod_w(j):
    """A one-hot feature vector: the image the first convolution sees (a forward hook) is one-hot at
    (j // 20, j % 20), and with all-ones 7x5 weights and zero bias the convolution's output is non-zero
    exactly on the 7 rows x 5 columns centred there (clipped to the image)."""
    net = ToG15CNN2D(600, 3).eval()
    with torch.no_grad():
        net.convs[0].weight.fill_(1.0)
        net.convs[0].bias.zero_()
    seen = {}
    net.convs[0].register_forward_hook(lambda mod, inp, out: seen.update(image=inp[0], out=out))
    x = torch.zeros(1, 1, 600)
    x[0, 0, j] = 1.0
    with torch.no_grad():
        net(x)
    r, c = j // 20, j % 20
    expected = torch.zeros(30, 20)
    expected[r, c] = 1.0
    assert torch.equal(seen["image"][0, 0], expected)
    support = torch.zeros(30, 20, dtype=torch.bool)
    support[max(r - 3, 0) : r + 4, max(c - 2, 0) : c + 3] = True
    for channel in seen["out"][0]:
        assert torch.equal(channel != 0, support)


def test_image_is_the_vector_row_by_row():
    x = torch.arange(600.0).reshape(1, 1, 600)
    img = ToG15CNN2D(600, 2).image(x)[0, 0]
    assert img[0].tolist() == list(range(20)) and img[1, 0] == 20 and img[29, 19] == 599
    img = ToG15CNN2D(600, 2, image_shape=(20, 30)).image(x)[0, 0]  # another shape: still row-major
    assert img.shape == (20, 30) and img[1, 0] == 30


class Reference(nn.Module):
    """The same layers as a plain NCHW nn.Sequential."""

    def __init__(self, net: ToG15CNN2D):
        super().__init__()
        layers = []
        for conv, norm in zip(net.convs, net.norms):
            layers += [conv, norm, nn.ReLU(), nn.MaxPool2d(net.pool)]
        self.body = nn.Sequential(*layers, nn.Flatten(), net.fc1, nn.ReLU(), nn.Dropout(net.dropout), net.fc2)
        self.shape = net.image_shape

    def forward(self, x):
        return self.body(x.reshape(len(x), 1, *self.shape).contiguous())


@pytest.mark.parametrize("batch_norm", [True, False])
def test_matches_a_plain_nchw_network(batch_norm):
    """Channels-last maps and eval chunking change speed only: train-mode logits (same dropout mask),
    and eval logits of more than EVAL_CHUNK samples, equal the plain network's."""
    torch.manual_seed(0)
    net = ToG15CNN2D(600, 6, batch_norm=batch_norm)
    ref = Reference(net)  # shares the parameters
    x = torch.randn(EVAL_CHUNK * 2 + 3, 1, 600) * 2 + 0.5
    torch.manual_seed(1)
    a = net.train()(x)
    torch.manual_seed(1)
    b = ref.train()(x)
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)
    with torch.no_grad():
        torch.testing.assert_close(net.eval()(x), ref.eval()(x), rtol=1e-4, atol=1e-4)


def test_trains_on_a_separable_toy_problem():
    torch.manual_seed(0)
    x = torch.randn(256, 1, 600)
    y = (x[:, 0, 137] > 0).long() + 2 * (x[:, 0, 400] > 0).long()
    net = ToG15CNN2D(600, 4)
    opt = torch.optim.SGD(net.parameters(), lr=0.05, momentum=0.9)
    for _ in range(60):
        opt.zero_grad()
        F.cross_entropy(net(x), y).backward()
        opt.step()
    with torch.no_grad():
        assert (net.eval()(x).argmax(1) == y).float().mean() > 0.9


def test_same_seed_same_outputs():
    x = torch.randn(6, 1, 600)
    outs = []
    for _ in range(2):
        torch.manual_seed(7)
        net = ToG15CNN2D(600, 8)
        outs.append(net(x))  # train mode: dropout from the same seed
        outs.append(net.eval()(x))
    assert torch.equal(outs[0], outs[2]) and torch.equal(outs[1], outs[3])
    torch.manual_seed(8)
    assert not torch.equal(ToG15CNN2D(600, 8).eval()(x), outs[1])


def test_invalid_arguments():
    """Each refusal is one ConfigError line naming the setting as the YAML (or the command line) writes it."""
    cases = [
        (
            dict(n_features=800),
            r"model\.net\.image_shape=\[30, 20\] is not allowed: it holds 600 values, but there are 800 features",
        ),
        (dict(branches=3), r"^branches=3 is not allowed: ToG15CNN2D takes branches=1"),
        (
            dict(kernels=((6, 5), (5, 5))),
            r"^model\.net\.kernels=\[\[6, 5\], \[5, 5\]\] is not allowed: .*odd kernel sizes",
        ),
        (
            dict(channels=(16,)),
            r"^model\.net\.kernels=.* is not allowed: it must list one size .* per entry of model\.net\.channels",
        ),
        (
            dict(channels=(4,) * 5, kernels=(3,) * 5),
            r"^model\.net\.image_shape=\[30, 20\] is not allowed: it is too small",
        ),
        (dict(activation="gelu"), r"^model\.net\.activation=gelu is not allowed: choose one of \['relu', "),
        (dict(padding="full"), r"^model\.net\.padding=full is not allowed: choose one of \['same', 'valid'\]"),
        (dict(dropout=1.0), r"^model\.net\.dropout=1\.0 is not allowed: it must be a number in \[0, 1\)"),
        (dict(hidden=0), r"^model\.net\.hidden=0 is not allowed: it must be an integer >= 1"),
        (dict(batch_norm="yes"), r"^model\.net\.batch_norm=yes is not allowed: it must be true or false"),
    ]
    for kwargs, message in cases:
        args = {"n_features": 600, "n_classes": 5, **kwargs}
        with pytest.raises(ConfigError, match=message):
            ToG15CNN2D(**args)
    net = ToG15CNN2D(600, 5)
    for shape in [(4, 600), (4, 3, 600), (4, 1, 599), (4, 1, 30, 20)]:
        with pytest.raises(ValueError, match=re.escape("expected input of shape (N, 1, 600)")) as err:
            net(torch.randn(*shape))
        assert f"got {shape}" in str(err.value)


# --- configuration and the CLI ---------------------------------------------------------------------


def test_config_selects_600_features_and_one_branch():
    cfg = compose_run("model=cnn2d")
    assert (cfg.model.name, cfg.features.name, cfg.branches) == ("cnn2d", "f600", 1)
    assert list(cfg.model.net.image_shape) == [30, 20] and [list(k) for k in cfg.model.net.kernels][0] == [7, 5]
    assert compose_run("model=cnn2d", "features=f800").features.name == "f800"  # the command line still wins
    assert (compose_run().features.name, compose_run().branches) == ("f800", 3)  # cnn1d untouched


def test_config_builds_the_network():
    from hydra.utils import instantiate

    cfg = compose_run("model=cnn2d")
    net = instantiate(cfg.model.net)(n_features=600, n_classes=4, branches=cfg.branches)  # as NetFitter does
    assert isinstance(net, ToG15CNN2D) and net(torch.randn(3, 1, 600)).shape == (3, 4)


@pytest.fixture
def env(tmp_path, cache_dir):
    """Subprocess environment: this test's MLflow store and logs, the session's feature cache."""
    return {
        **os.environ,
        "MESHSEG_CACHE_DIR": str(cache_dir),
        "MESHSEG_MLFLOW_DIR": str(tmp_path / "mlruns"),
        "MESHSEG_LOG_DIR": str(tmp_path / "logs"),
        "OMP_NUM_THREADS": "1",
    }


# 5 small tables: the real f600 features in a few seconds
SMALL = [
    "budget=smoke",
    "dataset.meshes_per_category=5",
    "dataset.max_faces=2000",
    "category=table",
    "trainer.threads=1",
    "workers=1",
]


def meshseg_run(env, *overrides):
    return subprocess.run(
        [sys.executable, "-m", "meshseg.run", *overrides],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )


def test_cli_run_finishes_tagged_cnn2d_f600_one_branch(env, tmp_path):
    r = meshseg_run(env, "model=cnn2d", *SMALL, "fold=1")
    assert r.returncode == 0, r.stderr[-3000:]
    client = MlflowClient(f"sqlite:///{tmp_path}/mlruns/mlflow.db")
    (run,) = client.search_runs([client.get_experiment_by_name("meshseg").experiment_id])
    assert run.info.status == "FINISHED"
    tags = run.data.tags
    assert (tags["model"], tags["features"], tags["branches"], tags["budget"]) == ("cnn2d", "f600", "1", "smoke")
    assert run.data.params["model.net._target_"] == "meshseg.models.cnn2d.ToG15CNN2D"
    assert 0 <= run.data.metrics["test/acc"] <= 1


def test_cli_rejects_other_branch_counts(env, tmp_path):
    r = meshseg_run(env, "model=cnn2d", "branches=3", *SMALL)
    assert r.returncode == 1
    assert "error: branches=3 is not allowed with model=cnn2d: it takes branches=1" in r.stderr
    db = tmp_path / "mlruns" / "mlflow.db"
    if db.exists():  # checked before any run starts
        client = MlflowClient(f"sqlite:///{db}")
        exp = client.get_experiment_by_name("meshseg")
        assert exp is None or client.search_runs([exp.experiment_id]) == []
