"""model=gbdt (not in the paper): gradient-boosted trees on the same features, X^1..X^B concatenated, early
stopping on whole training meshes held out. Five small synthetic figures, a cheap feature set, budget=smoke."""

import dataclasses

import numpy as np
import pytest
from test_baselines import N_CLASSES, SMALL, finished, paths, source  # noqa: F401  (fixtures)
from test_run import compose_run

from meshseg.data.splits import Fold
from meshseg.errors import ConfigError
from meshseg.models.gbdt import GradientBoostedTrees, inner_split
from meshseg.training.context import TrainContext
from meshseg.training.fit import fit_predict
from meshseg.training.fitters import build_fitter

TRAIN = ("1", "2", "3", "4")


def fit(source, test=("0",), seed=0, *overrides):  # noqa: F811
    cfg = compose_run(*SMALL, "model=gbdt", *overrides)
    ctx = TrainContext.from_config(cfg.budget, cfg.trainer, seed)
    fold_source = dataclasses.replace(source, fold=Fold(0, TRAIN, tuple(test)), branches=cfg.branches)
    fitter = build_fitter(cfg.model, ctx)
    return fit_predict(fold_source, fitter, cfg.budget.faces_per_mesh, workers=1), fitter


def test_gbdt_runs_a_smoke_fold_through_meshseg_run(paths):  # noqa: F811
    from meshseg.run import run

    acc = run(compose_run(*SMALL, "model=gbdt", "fold=0", *paths)).acc
    client, (r,) = finished(paths, "gbdt")
    assert r.data.tags["branches"] == "3" and r.data.params["model.trees.library"] == "lightgbm"
    assert np.isclose(r.data.metrics["test/acc"], acc) and acc > 0.6  # 4 parts: chance is 0.25


def test_same_seed_same_probabilities_and_the_seed_matters(source):  # noqa: F811
    (first, a), (again, _), (other, _) = fit(source), fit(source), fit(source, ("0",), 1)
    (p,) = first.probabilities
    assert p.dtype == np.float32 and p.shape == (first.meshes[0].n_faces, N_CLASSES)
    assert np.allclose(p.sum(axis=1), 1, atol=1e-5) and np.array_equal(p, again.probabilities[0])
    assert a.rounds_ >= 1 and not np.array_equal(p, other.probabilities[0])


def test_early_stopping_holds_out_training_meshes_only(source):  # noqa: F811
    for seed in range(4):
        (preds, fitter) = fit(source, ("0",), seed, "model.trees.inner_meshes=0.5")
        held = set(fitter.inner_meshes_)
        assert len(held) == 2 and held <= set(TRAIN) and "0" not in held  # never the test mesh
    # the split is by mesh: every row of a held-out mesh is held out, none of the others
    groups = np.repeat(np.arange(6), 10)
    inner = inner_split(groups, 0.2, seed=0)
    assert len(inner) == 1 and np.array_equal(inner, inner_split(groups, 0.2, seed=0))
    assert {tuple(inner_split(groups, 0.5, seed=s)) for s in range(6)} != {tuple(inner)}  # seeded, not fixed
    assert len(inner_split(np.array([0, 0, 1]), 0.99, 0)) == 1  # one mesh is always left to train on
    with pytest.raises(ConfigError, match="model=gbdt needs at least 2 training meshes"):
        inner_split(np.zeros(5, int), 0.2, 0)


def test_multi_scale_inputs_are_concatenated_and_absent_classes_get_zero():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(300, 3, 4)).astype(np.float32)
    y = np.where(X[:, 2, 1] > 0, 2, 0)  # only the third scale separates the classes; class 1 never seen
    model = GradientBoostedTrees(3, seed=0, early_stopping_rounds=5).fit(X, y, np.repeat(np.arange(6), 50))
    p = model.predict_proba(X)
    assert p.shape == (300, 3) and (p[:, 1] == 0).all() and (p.argmax(axis=1) == y).mean() > 0.95


def test_bad_tree_settings_are_refused_when_built():
    ctx = TrainContext.from_config(compose_run("budget=smoke").budget, compose_run().trainer, 0)
    for bad, rule in [
        ("model.trees.inner_meshes=0", "fraction in \\(0, 1\\)"),
        ("model.trees.library=catboost", "choose one of \\['lightgbm'\\]"),
        ("model.trees.feature_fraction=1.5", "in \\(0, 1\\]"),
    ]:
        with pytest.raises(ConfigError, match=f"{bad.split('=')[0]}=.* is not allowed: .*{rule}"):
            build_fitter(compose_run("model=gbdt", bad).model, ctx)
