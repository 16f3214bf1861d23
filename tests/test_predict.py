"""`python -m meshseg.predict`: a fold's logged model labels a mesh file exactly as the run labelled it."""

import csv
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml
from conftest import REPO
from mlflow import MlflowClient
from omegaconf import OmegaConf

from meshseg.data.datasets import build_dataset
from meshseg.data.io import read_psb_labels, read_seg, write_off
from meshseg.metrics import area_weighted_accuracy


@pytest.fixture(scope="module")
def smoke_run(smoke_store):
    """A cnn1d run of the smoke store, its per-mesh table and its config."""
    client = MlflowClient(f"sqlite:///{smoke_store}/mlflow.db")
    exp = client.get_experiment_by_name("meshseg")
    run = client.search_runs([exp.experiment_id], "tags.model = 'cnn1d' and tags.branches = '3'")[0]
    with open(client.download_artifacts(run.info.run_id, "per_mesh.csv"), newline="") as f:
        rows = list(csv.DictReader(f))
    config = yaml.safe_load(open(client.download_artifacts(run.info.run_id, "config.yaml")))
    return run, rows, config


def predict(smoke_store, cache_dir, *args):
    env = {**os.environ, "MESHSEG_CACHE_DIR": str(cache_dir)}
    uri = f"tracking.uri=sqlite:///{smoke_store}/mlflow.db"
    return subprocess.run(
        [sys.executable, "-m", "meshseg.predict", *args, uri],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_predict_reproduces_the_runs_own_per_mesh_accuracy(smoke_store, cache_dir, smoke_run, tmp_path):
    run, rows, config = smoke_run
    mesh = build_dataset(OmegaConf.create(config["dataset"])).load(config["category"], rows[0]["mesh"])
    write_off(tmp_path / "m.off", mesh.vertices, mesh.faces)  # %.17g: the same geometry, the same features
    out, seg, png = tmp_path / "m_labels.txt", tmp_path / "m.seg", tmp_path / "m.png"
    r = predict(smoke_store, cache_dir, f"run_id={run.info.run_id}", f"mesh={tmp_path / 'm.off'}", f"out={out}")
    assert r.returncode == 0, r.stderr[-3000:]
    labels, names = read_psb_labels(out, mesh.n_faces)
    pred = np.array([mesh.label_names.index(n) for n in names])[labels]
    acc = area_weighted_accuracy(pred, mesh.labels, mesh.face_areas)
    assert acc == pytest.approx(float(rows[0]["acc"]), abs=1e-12)  # same mesh, same model: the run's figure
    # .seg: one label index per face (synthetic labels are names, not numbers); a PNG when asked
    r = predict(
        smoke_store, cache_dir, f"run_id={run.info.run_id}", f"mesh={tmp_path / 'm.off'}", f"out={seg}", f"render={png}"
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert np.array_equal(read_seg(seg, mesh.n_faces), pred)
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_predict_errors_are_one_line(smoke_store, cache_dir, smoke_run, tmp_path):
    run, _, _ = smoke_run
    bad = tmp_path / "bad.off"
    bad.write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n")  # a vertex and the face missing
    r = predict(smoke_store, cache_dir, f"run_id={run.info.run_id}", f"mesh={bad}", f"out={tmp_path / 'x.txt'}")
    assert r.returncode != 0 and r.stderr.strip().startswith(f"error: {bad}") and "Traceback" not in r.stderr
    good = tmp_path / "tet.off"
    write_off(good, np.eye(4, 3), np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]))
    r = predict(smoke_store, cache_dir, "run_id=0123456789abcdef", f"mesh={good}", f"out={tmp_path / 'x.txt'}")
    assert r.returncode != 0 and "run_id=0123456789abcdef: no such run" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x.txt").exists()
