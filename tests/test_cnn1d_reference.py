"""One network spec, two implementations: `model=cnn1d` trains the fast `MultiBranchCNN1D`,
`model=cnn1d_reference` the readable `PaperCNN1D`, from the same settings, checked once
(`CNN1DSettings`) when the method is built, before any data is read.

The fold runs on five small synthetic figures (4 classes), a cheap feature set and budget=smoke, one
thread; the feature cache is shared by the session."""

from __future__ import annotations

import numpy as np
import pytest
from omegaconf import OmegaConf
from test_baselines import SMALL, compose_run  # five small figures, cheap features, budget=smoke

from meshseg.data.datasets import build_dataset
from meshseg.data.splits import Fold
from meshseg.errors import ConfigError
from meshseg.features.sets import FeatureSet
from meshseg.metrics import area_weighted_accuracy
from meshseg.models.cnn1d import MultiBranchCNN1D, PaperCNN1D
from meshseg.training.context import TrainContext
from meshseg.training.data import FeatureSource
from meshseg.training.fit import fit_predict
from meshseg.training.fitters import build_fitter


def fitter_for(*overrides):
    cfg = compose_run(*overrides)
    return build_fitter(cfg.model, TrainContext.from_config(cfg.budget, cfg.trainer, cfg.seed))


def test_the_reference_is_cnn1d_with_the_readable_network():
    fast, ref = (OmegaConf.to_container(compose_run(f"model={m}")) for m in ("cnn1d", "cnn1d_reference"))
    assert ref["model"].pop("name") == "cnn1d_reference" and fast["model"].pop("name") == "cnn1d"
    assert ref["model"]["net"].pop("_target_") == "meshseg.models.cnn1d.PaperCNN1D"
    assert fast["model"]["net"].pop("_target_") == "meshseg.models.cnn1d.MultiBranchCNN1D"
    assert ref == fast  # every other setting of the run, the network's and the optimiser's included


def test_a_fold_trains_alike_with_either_network(cache_dir):
    """Same seed, same fold: both start from the same weights, see the same batches and dropout masks, so
    they end with the same predictions up to float rounding, well above chance (0.25 for 4 parts)."""
    cfg = compose_run(*SMALL)
    fold = Fold(0, ("1", "2", "3"), ("0", "4"))
    source = FeatureSource(
        build_dataset(cfg.dataset), "figure", FeatureSet.from_config(cfg.features), str(cache_dir), 3, fold=fold
    )
    folds = {}
    for model in ("cnn1d", "cnn1d_reference"):
        c = compose_run(*SMALL, f"model={model}")
        ctx = TrainContext.from_config(c.budget, c.trainer, 0)
        folds[model] = fit_predict(source, build_fitter(c.model, ctx), c.budget.faces_per_mesh, workers=1)
    fast, ref = folds["cnn1d"], folds["cnn1d_reference"]
    assert isinstance(fast.parts["net"], MultiBranchCNN1D) and isinstance(ref.parts["net"], PaperCNN1D)
    assert fast.counts == ref.counts
    for mesh, p_fast, p_ref in zip(fast.meshes, fast.probabilities, ref.probabilities):
        np.testing.assert_allclose(p_fast, p_ref, rtol=0, atol=1e-4)  # measured: 4e-7
        acc = [area_weighted_accuracy(p.argmax(1), mesh.labels, mesh.face_areas) for p in (p_fast, p_ref)]
        assert acc[0] > 0.5 and abs(acc[0] - acc[1]) < 0.01  # measured: 0.77 and 0.69, equal to 1e-16


@pytest.mark.parametrize("model", ["cnn1d", "cnn1d_reference"])
@pytest.mark.parametrize(
    "override, message",
    [
        ("model.net.hidden=-1", "model.net.hidden=-1 is not allowed: it must be an integer >= 1"),
        (
            "model.net.kernels=[15,0]",
            "model.net.kernels=[15, 0] is not allowed: it must be a non-empty list of integers >= 1",
        ),
        (
            "model.net.kernels=[15]",
            "model.net.kernels=[15] is not allowed: it must give one size per entry of model.net.channels",
        ),
        ("model.net.dropout=1.5", "model.net.dropout=1.5 is not allowed: it must be a number in [0, 1)"),
        ("model.net.negative_slope=-0.2", "model.net.negative_slope=-0.2 is not allowed: it must be a number >= 0"),
        ("model.net.pool=0", "model.net.pool=0 is not allowed: it must be an integer >= 1"),
        ("+model.net.width=3", "model.net.width is not a setting of model.net: it takes ['channels', 'kernels'"),
    ],
)
def test_build_fitter_refuses_a_bad_network_setting_without_data(model, override, message):
    with pytest.raises(ConfigError) as err:
        fitter_for(f"model={model}", override)
    assert str(err.value).startswith(message)


@pytest.mark.parametrize(
    "model, override, message",
    [
        ("cnn2d", "model.net.hidden=-1", "model.net.hidden=-1 is not allowed: it must be an integer >= 1"),
        (
            "cnn2d",
            "model.net.kernels=[[7,5],[4,5]]",
            "model.net.kernels=[[7, 5], [4, 5]] is not allowed: model.net.padding=same needs odd",
        ),
        ("cnn2d", "model.net.image_shape=[2,2]", "model.net.image_shape=[2, 2] is not allowed: it is too small for 2"),
        ("cnn2d", "model.net.activation=gelu", "model.net.activation=gelu is not allowed: choose one of ['relu'"),
        ("pca_nn", "model.net.n_components=0", "model.net.n_components=0 is not allowed: it must be an integer >= 1"),
        ("pca_nn", "model.net.activation=swish", "model.net.activation=swish is not allowed: choose one of ['tanh'"),
        ("rf", "model.forest.n_estimators=0", "model.forest.n_estimators=0 is not allowed: it must be an integer >= 1"),
        ("rf", "model.forest.max_features=half", "model.forest.max_features=half is not allowed: choose one of"),
        (
            "ae_rf",
            "model.forest.max_depth=-2",
            "model.forest.max_depth=-2 is not allowed: it must be an integer >= 1 or null",
        ),
    ],
)
def test_build_fitter_refuses_the_other_models_bad_settings(model, override, message):
    with pytest.raises(ConfigError) as err:
        fitter_for(f"model={model}", override)
    assert str(err.value).startswith(message)


@pytest.mark.parametrize("model", ["cnn1d", "cnn1d_reference", "cnn2d", "pca_nn", "rf", "ae_rf", "ae_nn"])
def test_the_shipped_settings_pass(model):
    assert fitter_for(f"model={model}") is not None


@pytest.mark.parametrize("network", [MultiBranchCNN1D, PaperCNN1D])
def test_both_networks_refuse_alike_what_needs_the_data(network):
    with pytest.raises(ConfigError, match=r"^branches=5 is not allowed: the 1D CNN takes 1\.\.4"):
        network(800, 8, branches=5)
    with pytest.raises(ConfigError, match=r"^3 features are too few for 2 poolings by 2"):
        network(3, 8, branches=1)
    with pytest.raises(ConfigError, match=r"^model\.net\.hidden=0 is not allowed"):
        network(800, 8, hidden=0)
