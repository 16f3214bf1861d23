"""A `-m` sweep is a parent run with its fold runs nested under it (meshseg.tracking.sweeps): one parent per sweep,
found again by a rerun (which adds neither parent nor fold), agreed on by sweeps started at once, and no fold to
the report, the results export or any search for fold runs."""

import json
import os
import subprocess
import sys
import threading
import time

import pytest
from conftest import REPO
from mlflow import MlflowClient

from meshseg.report.runs import finished_by_hash
from meshseg.results import export
from meshseg.tracking import SWEEP_KEY, Tracker, open_parent, search_runs, sweep_key

SMALL = ["dataset.meshes_per_category=5", "features.groups=[curvature,pca,gc]", "features.name=local", "budget=smoke"]
PARENT_RUN_ID = "mlflow.parentRunId"


def every_run(store) -> list:
    """Every run of the store, parents too (MLflow's own search, not meshseg's)."""
    client = MlflowClient(f"sqlite:///{store}/mlflow.db")
    return client.search_runs([client.get_experiment_by_name("meshseg").experiment_id])


def sweep(tmp_path, cache_dir, *overrides):
    env = {
        **os.environ,
        "MESHSEG_CACHE_DIR": str(cache_dir),
        "MESHSEG_MLFLOW_DIR": str(tmp_path / "mlruns"),
        "MESHSEG_LOG_DIR": str(tmp_path / "logs"),
    }
    args = [sys.executable, "-m", "meshseg.run", *SMALL, *overrides, "-m"]
    r = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout + r.stderr


@pytest.mark.processes
def test_a_sweep_of_two_categories_is_one_parent_with_its_folds_nested_and_a_rerun_adds_none(
    smoke_store, tmp_path, cache_dir
):
    # (the smoke store is made first: these folds' features are then in the session's cache)
    # joblib's worker processes make the fold runs: the parent's id reaches them through the environment
    launcher = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "trainer.threads=1"]
    sweep(tmp_path, cache_dir, "category=cup,table", "fold=0", *launcher)
    store = tmp_path / "mlruns"
    (parent,) = [r for r in every_run(store) if SWEEP_KEY in r.data.tags]
    folds = [r for r in every_run(store) if SWEEP_KEY not in r.data.tags]
    assert sorted(r.data.tags["category"] for r in folds) == ["cup", "table"]
    assert {r.data.tags[PARENT_RUN_ID] for r in folds} == {parent.info.run_id}
    assert parent.info.status == "FINISHED" and "config_hash" not in parent.data.tags  # no fold, no identity
    # the parent carries the sweep's command, its settings and its summary (the folds' own accuracies)
    settings = [*SMALL, "category=cup,table", "fold=0"]
    assert parent.data.params == dict(s.split("=", 1) for s in settings)
    assert json.loads(parent.data.tags["sweep_overrides"]) == settings
    note = parent.data.tags["mlflow.note.content"]
    assert note.startswith("`python -m meshseg.run -m ") and "sweep: 2 ran, 0 skipped, 0 failed" in note
    m = parent.data.metrics
    assert (m["sweep/ran"], m["sweep/skipped"], m["sweep/failed"]) == (2, 0, 0)
    for r in folds:
        assert m[f"test/acc/{r.data.tags['category']}"] == pytest.approx(r.data.metrics["test/acc"])
    # meshseg's searches for fold runs do not see it
    tracker = Tracker(f"sqlite:///{store}/mlflow.db", "meshseg")
    fold_ids = {r.info.run_id for r in folds}
    assert {r.info.run_id for r in tracker.runs()} == fold_ids
    assert {r.info.run_id for r in search_runs(tracker.uri, "meshseg")} == fold_ids
    assert {r.info.run_id for r in finished_by_hash(tracker.uri, "meshseg").values()} == fold_ids

    # the same sweep again, settings in another order, on another launcher: the same parent, no new run
    out = sweep(tmp_path, cache_dir, "fold=0", "category=cup,table")
    assert out.count("skip:") == 2
    again = every_run(store)
    assert {r.info.run_id for r in again} == fold_ids | {parent.info.run_id}
    (parent,) = [r for r in again if SWEEP_KEY in r.data.tags]
    m = parent.data.metrics
    assert parent.info.status == "FINISHED" and (m["sweep/ran"], m["sweep/skipped"]) == (0, 2)


def test_the_smoke_stores_sweeps_are_parents_the_report_and_export_ignore(smoke_store, tmp_path):
    parents = [r for r in every_run(smoke_store) if SWEEP_KEY in r.data.tags]
    assert len(parents) == 2  # conftest's two sweeps: cnn1d 1B and 3B, and rf
    tracker = Tracker(f"sqlite:///{smoke_store}/mlflow.db", "meshseg")
    folds = tracker.runs()
    assert len(folds) == 18 and {r.data.tags[PARENT_RUN_ID] for r in folds} == {p.info.run_id for p in parents}
    assert len(finished_by_hash(tracker.uri, "meshseg")) == 18
    assert export(tracker, tmp_path / "results") == (18, 0)  # one record per fold, none for a parent


@pytest.mark.processes
def test_sweeps_of_one_study_started_at_once_agree_on_one_parent(tmp_path):
    """Four sweeps of one identity open their parent at once, five times over (one key each): every one gets the
    same kept parent, and no other parent survives."""
    trackers = [Tracker(f"sqlite:///{tmp_path}/mlflow.db", "meshseg") for _ in range(4)]
    for trial in range(5):
        key, start, got, errors = f"k{trial}", threading.Barrier(len(trackers)), [], []

        def one(tracker, key=key, start=start, got=got, errors=errors):
            start.wait()
            try:
                got.append(open_parent(tracker, key, "sweep · a=1", {"sweep_overrides": "[]"}, {"a": "1"}))
            except Exception as e:  # a thread's exception would otherwise only be a warning
                errors.append(repr(e))

        threads = [threading.Thread(target=one, args=(t,)) for t in trackers]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=120)
        assert errors == []
        (parent,) = [r for r in every_run(tmp_path) if r.data.tags.get(SWEEP_KEY) == key]
        assert got == [parent.info.run_id] * 4 and parent.data.params == {"a": "1"}, trial
    # another sweep is another parent
    assert open_parent(trackers[0], "k9", "sweep · a=2", {}, {"a": "2"}) != parent.info.run_id


def test_a_parent_left_undecided_by_a_dead_sweep_is_passed_over(tmp_path):
    """A parent made but never kept (its sweep died at that moment) blocks nobody once PENDING_S old."""
    from meshseg.tracking import sweeps

    tracker = Tracker(f"sqlite:///{tmp_path}/mlflow.db", "meshseg")
    orphan = tracker._create("sweep · a=1", {SWEEP_KEY: "k"}).info.run_id
    sweeps.PENDING_S, pending = 0.5, sweeps.PENDING_S
    try:
        time.sleep(0.6)
        kept = open_parent(tracker, "k", "sweep · a=1", {}, {"a": "1"})
    finally:
        sweeps.PENDING_S = pending
    assert kept != orphan and open_parent(tracker, "k", "sweep · a=1", {}, {"a": "1"}) == kept


def test_a_sweeps_identity_is_its_settings_not_how_or_where_it_runs():
    key, settings = sweep_key(["model=cnn1d", "branches=1,3", "budget=smoke"], ("paths", "trainer.threads"))
    assert settings == ["model=cnn1d", "branches=1,3", "budget=smoke"]
    same = ["budget=smoke", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "model=cnn1d", "branches=1,3"]
    assert sweep_key([*same, "paths.cache_dir=/x", "trainer.threads=1"], ("paths", "trainer.threads"))[0] == key
    assert sweep_key(["model=cnn1d", "branches=1,3", "budget=cpu"], ("paths",))[0] != key
    assert sweep_key(["model=cnn1d", "branches=1,3", "budget=smoke", "seed=1"], ())[0] != key


def test_a_package_override_is_a_parent_param_mlflow_accepts(tmp_path, monkeypatch):
    # `model@model.stage1=cnn1d` (Hydra's group@package) once failed the sweep: MLflow allows no '@' in a param name
    from types import SimpleNamespace

    from meshseg.sweep import SWEEP_PARENT, SweepParent

    monkeypatch.delenv(SWEEP_PARENT, raising=False)  # open() sets it; the test's end takes it away again
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    tracking = SimpleNamespace(uri=uri, experiment="meshseg", artifact_dir=None, hash_exclude=["trainer"])
    overrides = ["model=stacked", "model@model.stage1=cnn1d", "+extra=1", "trainer.threads=1", "category=Vase"]
    parent = SweepParent.open([tracking], overrides)
    run = MlflowClient(uri).get_run(parent.run_id)
    assert run.data.params == {"model": "stacked", "model:model.stage1": "cnn1d", "extra": "1", "category": "Vase"}
    assert json.loads(run.data.tags["sweep_overrides"]) == [o for o in overrides if not o.startswith("trainer")]
