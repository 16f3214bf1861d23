"""model=gbdt (not in the paper): gradient-boosted trees on the same features, X^1..X^B concatenated, early
stopping on whole training meshes held out. Five small synthetic figures, a cheap feature set, budget=smoke."""

import dataclasses
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
from test_baselines import N_CLASSES, SMALL, finished, paths, source  # noqa: F401  (fixtures)
from test_run import compose_run

from meshseg.data.splits import Fold
from meshseg.errors import ConfigError
from meshseg.models.gbdt import GradientBoostedTrees, inner_split
from meshseg.timing import Timings
from meshseg.training.context import TrainContext
from meshseg.training.data import iter_test_inputs, mesh_groups
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
    assert r.data.metrics["gbdt/rounds"] >= 1  # what early stopping chose, with the run


def test_same_seed_same_probabilities_and_the_seed_matters(source):  # noqa: F811
    (first, a), (again, _), (other, _) = fit(source), fit(source), fit(source, ("0",), 1)
    (p,) = first.probabilities
    assert p.dtype == np.float32 and p.shape == (first.meshes[0].n_faces, N_CLASSES)
    assert np.allclose(p.sum(axis=1), 1, atol=1e-5) and np.array_equal(p, again.probabilities[0])
    assert a.rounds_ >= 1 and not np.array_equal(p, other.probabilities[0])


def test_early_stopping_holds_out_training_meshes_only(source):  # noqa: F811
    for seed in range(4):
        (preds, fitter) = fit(source, ("0",), seed, "model.trees.inner_meshes=0.5")
        held = set(fitter.held_out_)
        assert len(held) == 2 and held <= set(TRAIN) and "0" not in held  # never the test mesh
    # the split is by mesh: every row of a held-out mesh is held out, none of the others
    groups = np.repeat(np.arange(6), 10)
    inner = inner_split(groups, 0.2, seed=0)
    assert len(inner) == 1 and np.array_equal(inner, inner_split(groups, 0.2, seed=0))
    assert len({tuple(inner_split(groups, 0.5, seed=s)) for s in range(6)}) > 1  # seeded, not fixed
    assert len(inner_split(np.array([0, 0, 1]), 0.99, 0)) == 1  # one mesh is always left to train on
    with pytest.raises(ConfigError, match="model=gbdt needs at least 2 training meshes"):
        inner_split(np.zeros(5, int), 0.2, 0)


def test_the_first_trees_never_see_the_held_out_rows_and_the_refit_grows_the_chosen_rounds(monkeypatch):
    """The boosters `fit` grows, by the rows each is given: early stopping trains on the other meshes' rows
    and scores the held-out meshes' rows only; the refit then grows exactly the chosen rounds on every row."""
    rng = np.random.default_rng(0)
    groups = np.repeat(np.arange(6), 50)  # 6 meshes of 50 faces; 0.2 of them held out: 1 mesh
    X = rng.normal(size=(300, 2, 5)).astype(np.float32)
    y = (X[:, 0, 0] + 0.5 * rng.normal(size=300) > 0).astype(int) * 2  # noisy: early stopping stops early
    calls = []
    train = GradientBoostedTrees._train

    def spy(self, X, y, rounds, valid=None, bins=None):
        booster, record, data = train(self, X, y, rounds, valid, bins)
        calls.append((len(X), rounds, None if valid is None else len(valid[0]), booster.current_iteration()))
        assert (bins is None) == (valid is not None)  # the refit reuses the first fit's bin edges
        return booster, record, data

    monkeypatch.setattr(GradientBoostedTrees, "_train", spy)
    model = GradientBoostedTrees(3, seed=0, early_stopping_rounds=5, max_rounds=200).fit(X, y, groups)
    (first_rows, first_cap, valid_rows, _), (all_rows, refit_rounds, refit_valid, grown) = calls
    assert len(model.inner_) == 1 and (first_rows, valid_rows) == (250, 50) and first_cap == 200
    assert 1 <= model.rounds_ < 200 and len(model.curve_) == model.rounds_ + 5  # stopped 5 rounds after the best
    assert (all_rows, refit_rounds, refit_valid, grown) == (300, model.rounds_, None, model.rounds_)
    assert model.booster_.current_iteration() == model.rounds_


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


def test_held_out_meshes_are_predicted_by_the_trees_grown_without_them(source):  # noqa: F811
    """refine.search chooses on the held-out meshes' probabilities: those of the early-stopped trees, which
    never saw them (not the refitted ones, which did); without refit the two are one model."""
    (preds, fitter), (same, plain) = fit(source), fit(source, ("0",), 0, "model.trees.refit=false")
    trees = fitter.trees_
    assert trees.inner_booster_ is not trees.booster_ and plain.trees_.inner_booster_ is plain.trees_.booster_
    assert fitter.held_out_  # fit_predict predicts only the test meshes; the held-out ones when a refinement asks
    fold_source = dataclasses.replace(
        source, fold=Fold(0, TRAIN, ("0",)), branches=compose_run(*SMALL, "model=gbdt").branches
    )
    _, X = next(iter_test_inputs(fold_source, [fitter.held_out_[0]], preds.standardiser))
    inner, refitted = fitter.predict_held_out(X), fitter.predict_proba(X)
    meshes, probabilities = preds.predict_held_out(fold_source, Timings())  # what fit_refinement chooses on
    assert [m.id for m in meshes] == list(fitter.held_out_)
    np.testing.assert_array_equal(probabilities[0], inner)
    expected = trees.inner_booster_.predict(X.reshape(len(X), -1), num_iteration=trees.rounds_)
    np.testing.assert_allclose(inner[:, trees.classes_], expected, rtol=1e-6)
    assert not np.allclose(inner, refitted)
    _, X = next(iter_test_inputs(fold_source, [plain.held_out_[0]], same.standardiser))
    np.testing.assert_array_equal(plain.predict_held_out(X), plain.predict_proba(X))
    # the saved model keeps only the trees it predicts test meshes with
    restored = pickle.loads(pickle.dumps(fitter))
    np.testing.assert_array_equal(restored.predict_proba(X), fitter.predict_proba(X))
    with pytest.raises(RuntimeError, match="not kept in a saved model"):
        restored.predict_held_out(X)


def test_refine_search_chooses_on_held_out_training_meshes_through_meshseg_run(tmp_path, cache_dir):
    """model=gbdt with refine.search: the settings are chosen per fold on the held-out training meshes (never
    the test mesh), recorded as run metrics and refine_search.json; the test mesh is refined with them, and so
    is a new mesh by the fold's logged model. The grid leaves out the configured lam=2, so a run that refined
    with the configured settings would label the test mesh otherwise."""
    from meshseg.data.datasets import build_dataset
    from meshseg.features.sets import FeatureSet
    from meshseg.predict import load_run_model
    from meshseg.refine import build_refinement
    from meshseg.refine.search import SEARCH_RECORD
    from meshseg.run import run
    from meshseg.tracking import FoldRecord, Tracker

    store = [f"paths.mlflow_dir={tmp_path}/mlruns", f"paths.log_dir={tmp_path}/logs", f"paths.cache_dir={cache_dir}"]
    cfg = compose_run(*SMALL, "model=gbdt", "fold=0", "refine.search={lam:[0.0,8.0],omega:[0.0,2.0]}", *store)
    run(cfg)
    client, (r,) = finished(store, "gbdt")
    m, fold = r.data.metrics, json.loads(r.data.tags["fold_ids"])
    path = client.download_artifacts(r.info.run_id, FoldRecord.REFINE_SEARCH, str(tmp_path))
    searched = json.loads(Path(path).read_text())
    assert searched["held_out"] and set(searched["held_out"]) <= set(fold["train"])
    assert not set(searched["held_out"]) & set(fold["test"])  # never a test mesh
    rows = searched["grid"]
    assert [(g["lam"], g["omega"]) for g in rows] == [(0.0, 0.0), (0.0, 2.0), (8.0, 0.0), (8.0, 2.0)]
    best = max(rows, key=lambda g: g["score"])  # the first of equals
    assert (best["lam"], best["omega"]) == (m["refine/lam"], m["refine/omega"])
    assert np.isclose(m["refine/held_out_acc"], best["score"]) and len(best["per_mesh"]) == len(searched["held_out"])
    assert FoldRecord.REFINE_SEARCH == SEARCH_RECORD  # the artifact the refinement stage names
    # the values the search logged before it moved from run.py into the refinement stage (commit 0b4bc1f)
    assert (m["refine/lam"], m["refine/omega"]) == (8.0, 2.0)
    assert m["refine/held_out_acc"] == pytest.approx(0.9555690629804559, rel=1e-6)
    assert (m["test/acc"], m["test/acc_raw"]) == pytest.approx((0.9673417327150057, 0.8804367709833992), rel=1e-6)
    assert m["time/refine_search_s"] > 0 and m["time/predict_held_out_s"] > 0
    # the fold's model refines with the chosen settings, searching nothing, and labels the test mesh as the run did
    model, _ = load_run_model(Tracker(f"sqlite:///{tmp_path}/mlruns/mlflow.db", "meshseg"), r.info.run_id)
    assert (model.refine["lam"], model.refine["omega"], model.refine["search"]) == (best["lam"], best["omega"], None)
    (test_id,) = fold["test"]
    mesh = build_dataset(cfg.dataset).load("figure", test_id)
    arrays = np.load(client.download_artifacts(r.info.run_id, FoldRecord.PREDICTIONS, str(tmp_path)))
    P, _, labels = model.predict(mesh, str(cache_dir))
    np.testing.assert_array_equal(labels, arrays[f"labels_{test_id}"])
    configured = dataclasses.replace(build_refinement(cfg.refine), search=None)  # lam=2, omega=2: no grid point
    agd = mesh_groups(mesh, FeatureSet.from_config(cfg.features), configured.needs, str(cache_dir))
    assert not np.array_equal(configured(mesh, P, agd), labels)  # so the run did refine with the chosen ones


def test_refine_search_is_refused_for_a_model_that_holds_no_meshes_out():
    from meshseg.job import build_method

    with pytest.raises(ConfigError, match="refine.search is not allowed with model=cnn1d: it chooses on training"):
        build_method(compose_run(*SMALL, "model=cnn1d", "refine.search={lam:[1.0,2.0]}"))
