"""model=stacked (issue 53, not in the paper): stage 1 out of fold on the training meshes, context features of its
probabilities, stage 2 on [own inputs, context]. Five small synthetic figures, budget=smoke, as test_gbdt."""

import copy
import dataclasses
import json

import numpy as np
import pytest
from test_baselines import N_CLASSES, SMALL, finished, paths, source  # noqa: F401  (fixtures)
from test_run import compose_run

from meshseg.data.datasets import build_dataset
from meshseg.data.splits import Fold
from meshseg.errors import ConfigError
from meshseg.features.label_context import MeshContext
from meshseg.metrics import area_weighted_accuracy
from meshseg.training.context import TrainContext
from meshseg.training.fit import fit_predict
from meshseg.training.fitters import GbdtFitter, build_fitter
from meshseg.training.stacked import StackedFitter, inner_groups

TRAIN = ("1", "2", "3", "4")


def fit(source, test=("0",), seed=0, *overrides):  # noqa: F811
    cfg = compose_run(*SMALL, "model=stacked", "model.inner_folds=2", "branches=1", *overrides)
    ctx = TrainContext.from_config(cfg.budget, cfg.trainer, seed)
    fold_source = dataclasses.replace(source, fold=Fold(0, TRAIN, tuple(test)), branches=cfg.branches)
    fitter = build_fitter(cfg.model, ctx)
    return fit_predict(fold_source, fitter, cfg.budget.faces_per_mesh, workers=1), fitter


@pytest.fixture(scope="module")
def fitted(source):  # noqa: F811
    return fit(source)


def test_stage_one_never_predicts_a_mesh_it_trained_on_and_never_sees_the_test_mesh(fitted):
    preds, fitter = fitted
    assert len(fitter.inner_) == 2 and all(isinstance(f, GbdtFitter) for f in fitter.inner_)
    predicted = []
    for trained_on, held in fitter.inner_meshes_:
        assert not set(trained_on) & set(held)  # out of fold
        assert "0" not in trained_on and "0" not in held  # the test mesh is in no inner fold
        predicted += held
    assert sorted(predicted) == sorted(TRAIN)  # every training mesh predicted exactly once
    # what each inner model was fitted on, read back from the rows GBDT saw: its own meshes only
    for f, (trained_on, _) in zip(fitter.inner_, fitter.inner_meshes_):
        assert set(f.held_out_) <= set(trained_on)  # its early-stopping meshes are among its training meshes


def test_no_inner_model_labels_a_mesh_it_saw_and_each_fits_exactly_its_meshes_rows(source, monkeypatch):  # noqa: F811
    """Spy on every inner stage-1 model: the rows its fit got, and each mesh it labels (during the fit, its
    held-out group; then the test mesh, once per inner model under test_stage1=each). None is one it saw, and
    each fit gets exactly the outer training rows of its meshes."""
    trained, seen, labelled = {}, [], []
    real_fit, real_predict = GbdtFitter.fit, GbdtFitter.predict_mesh

    def spy_fit(self, train):
        trained[id(self)] = set(train.mesh_ids)
        seen.append((train.mesh_ids, len(train.y), set(np.unique(train.mesh_index).tolist())))
        return real_fit(self, train)

    def spy_predict(self, mesh, X):
        labelled.append((id(self), mesh.id))
        return real_predict(self, mesh, X)

    monkeypatch.setattr(GbdtFitter, "fit", spy_fit)
    monkeypatch.setattr(GbdtFitter, "predict_mesh", spy_predict)
    preds, fitter = fit(source)
    assert len(trained) == 2 and all(mesh not in trained[model] for model, mesh in labelled)
    assert sorted(mesh for _, mesh in labelled) == sorted([*TRAIN, "0", "0"])
    assert {model for model, mesh in labelled if mesh == "0"} == set(trained)  # each inner model, once
    for (ids, _, index), (trained_on, _) in zip(seen, fitter.inner_meshes_):
        assert ids == trained_on and index == set(range(len(ids)))
    assert sum(n for _, n, _ in seen) == preds.counts["train_samples"]  # two halves: every row once


def test_a_test_mesh_reaches_stage_two_through_each_inner_labelling(fitted, source):  # noqa: F811
    """test_stage1=each: stage 2 on the context of each inner model's labelling, its probabilities averaged;
    mean: stage 2 once, on the context of the inner models' mean probabilities. Worked out from the parts."""
    _, fitter = fitted
    mesh, scales = source.load("0")
    X = np.stack(scales, axis=1)
    surface = MeshContext(mesh.vertices, mesh.faces, fitter.features)
    each = [f.predict_mesh(mesh, X) for f in fitter.inner_]

    def stage2(P):
        return fitter.trees_.predict_proba(np.concatenate([X.reshape(len(X), -1), surface.features(P)], axis=1))

    by_hand = np.mean([stage2(P) for P in each], axis=0)
    np.testing.assert_allclose(fitter.predict_mesh(mesh, X), by_hand, rtol=1e-6)
    as_mean = copy.copy(fitter)  # the same fitted stack, read as test_stage1=mean
    as_mean.test_stage1 = "mean"
    once = stage2(np.mean(each, axis=0))
    np.testing.assert_allclose(as_mean.predict_mesh(mesh, X), once, rtol=1e-6)
    assert np.abs(once - by_hand).max() > 1e-4  # the two readings differ (a little, on this easy figure)


def test_same_seed_same_probabilities(fitted, source):  # noqa: F811
    preds, fitter = fitted
    again, _ = fit(source)
    (p,) = preds.probabilities
    assert p.shape == (preds.meshes[0].n_faces, N_CLASSES) and np.allclose(p.sum(axis=1), 1, atol=1e-5)
    assert np.array_equal(p, again.probabilities[0])
    assert fitter.fitted()["stacked/inner_folds"] == 2 and fitter.fitted()["stacked/stage2_rounds"] >= 1


def test_stage_two_uses_the_context(fitted):
    """The context columns come after the own inputs and stage 2 splits on some of them."""
    preds, fitter = fitted
    booster = fitter.trees_.booster_
    n_own = booster.num_feature() - len(fitter.features.names(N_CLASSES))
    gains = booster.feature_importance("gain")
    assert n_own > 0 and gains[n_own:].sum() > 0


def test_inner_groups_are_seeded_and_cover_every_mesh():
    groups = inner_groups(7, 3, seed=0)
    assert sorted(np.concatenate(groups).tolist()) == list(range(7)) and [len(g) for g in groups] == [3, 2, 2]
    assert all(np.array_equal(a, b) for a, b in zip(groups, inner_groups(7, 3, seed=0)))
    assert len({tuple(inner_groups(7, 3, seed=s)[0]) for s in range(5)}) > 1
    with pytest.raises(ConfigError, match="model.inner_folds=5: needs 2 <= inner_folds"):
        inner_groups(4, 5, seed=0)


@pytest.mark.parametrize(
    "override, message",
    [
        ("model.inner_folds=1", "model.inner_folds=1: at least 2"),
        ("model.test_stage1=median", r"model.test_stage1=median: one of \['each', 'mean'\]"),
        ("model.context_features.radii=[-1]", "every radius must be > 0"),
        ("model.stage2.learning_rate=0", "learning_rate"),
        ("model.stage1.trees.num_leaves=1", "num_leaves"),
    ],
)
def test_bad_settings_are_refused_when_the_method_is_built(override, message):
    cfg = compose_run(*SMALL, "model=stacked", override)
    with pytest.raises(ConfigError, match=message):
        build_fitter(cfg.model, TrainContext.from_config(cfg.budget, cfg.trainer, 0))


def test_more_inner_folds_than_training_meshes_is_refused_when_the_job_is_resolved(paths):  # noqa: F811
    from meshseg.job import FoldJob

    # 5 figures, 5-fold: 4 training meshes; refused before any feature is computed or any run is created
    cfg = compose_run(*SMALL, "model=stacked", "model.inner_folds=5", "branches=1", "fold=0", *paths)
    with pytest.raises(ConfigError, match=r"model.inner_folds=5: needs 2 <= inner_folds <= .* \(4\)"):
        FoldJob.from_config(cfg)
    FoldJob.from_config(compose_run(*SMALL, "model=stacked", "model.inner_folds=4", "branches=1", "fold=0", *paths))


def test_a_stacked_run_is_logged_and_its_model_predicts_a_mesh(paths, tmp_path):  # noqa: F811
    from meshseg.predict import load_run_model
    from meshseg.run import run
    from meshseg.tracking import Tracker

    cfg = compose_run(*SMALL, "model=stacked", "model.inner_folds=2", "branches=1", "fold=0", *paths)
    acc = run(cfg).acc
    client, (r,) = finished(paths, "stacked")
    assert np.isclose(r.data.metrics["test/acc"], acc) and acc > 0.6  # 4 parts: chance is 0.25
    assert r.data.metrics["stacked/stage2_rounds"] >= 1 and r.data.params["model.stage1.name"] == "gbdt"
    assert {"stacked/stage1_s", "stacked/context_s", "stacked/stage2_s"} <= set(r.data.metrics)
    tracker = Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir)
    model, _ = load_run_model(tracker, r.info.run_id)
    assert isinstance(model.fitter, StackedFitter)
    # the logged model labels the fold's test meshes as the run did: the run's accuracy, to the last digits
    dataset = build_dataset(cfg.dataset)
    meshes = [dataset.load("figure", m) for m in json.loads(r.data.tags["fold_ids"])["test"]]
    accs = [area_weighted_accuracy(model.predict(m, cfg.paths.cache_dir)[2], m.labels, m.face_areas) for m in meshes]
    assert np.mean(accs) == pytest.approx(acc, abs=1e-12)


def test_of_meshes_keeps_exactly_the_rows_of_those_meshes_renumbered():
    from meshseg.training.data import Standardiser, TrainSet

    X = np.arange(12, dtype=np.float32).reshape(6, 1, 2)
    index = np.array([0, 0, 1, 1, 2, 2], dtype=np.int32)
    y, faces = np.array([0, 1, 2, 3, 0, 1]), np.array([5, 7, 1, 2, 0, 3])
    train = TrainSet(X, y, Standardiser().fit(X), 6, 4, None, index, ("a", "b", "c"), faces)
    part = train.of_meshes([2, 0])
    assert part.mesh_ids == ("c", "a") and part.mesh_index.tolist() == [1, 1, 0, 0]
    assert part.X[:, 0, 0].tolist() == [0, 2, 8, 10] and part.y.tolist() == [0, 1, 0, 1]
    assert part.faces.tolist() == [5, 7, 0, 3] and part.standardiser is train.standardiser
