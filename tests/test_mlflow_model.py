"""Each fold's model as an MLflow logged model (meshseg.pyfunc): `mlflow.pyfunc.load_model("runs:/<id>/model")`
labels a mesh as `meshseg.predict` does, offline; `meshseg.predict` still reads runs from before logged models."""

import csv
import json
import socket
from pathlib import Path

import mlflow
import numpy as np
import pytest
import yaml
from omegaconf import OmegaConf

from meshseg.data.datasets import build_dataset
from meshseg.data.io import read_psb_labels, write_off
from meshseg.metrics import area_weighted_accuracy
from meshseg.tracking import FoldRecord, Tracker


@pytest.fixture(scope="module")
def fold(smoke_store):
    """A cnn1d 3B run of the smoke store, its first test mesh and that mesh's accuracy in the run's table."""
    tracker = Tracker(f"sqlite:///{smoke_store}/mlflow.db", "meshseg")
    (run, *_) = tracker.runs("tags.model = 'cnn1d' and tags.branches = '3'")
    with open(tracker.client.download_artifacts(run.info.run_id, FoldRecord.PER_MESH), newline="") as f:
        row = next(csv.DictReader(f))
    config = yaml.safe_load(open(tracker.client.download_artifacts(run.info.run_id, FoldRecord.CONFIG)))
    mesh = build_dataset(OmegaConf.create(config["dataset"])).load(config["category"], row["mesh"])
    return tracker, run, mesh, float(row["acc"])


@pytest.fixture
def offline(monkeypatch):
    """No connection to anywhere: a model that downloads (an environment, its requirements) fails."""

    def refuse(self, address):
        raise OSError(f"no network in this test: connect to {address}")

    monkeypatch.setattr(socket.socket, "connect", refuse)


def test_the_logged_model_labels_a_mesh_as_meshseg_predict_does(fold, cache_dir, tmp_path, offline):
    from meshseg.predict import main as predict_main

    tracker, run, mesh, acc = fold
    run_id = run.info.run_id
    # meshseg.predict on the mesh as a file, labels written: it finds the model in the store it is given (MLflow's
    # own global tracking uri may name another)
    mlflow.set_tracking_uri((tmp_path / "another store").as_uri())
    write_off(tmp_path / "m.off", mesh.vertices, mesh.faces)
    labels_file = tmp_path / "m_labels.txt"
    argv = [f"run_id={run_id}", f"mesh={tmp_path / 'm.off'}", f"out={labels_file}"]
    predict_main([*argv, f"tracking.uri={tracker.uri}", f"paths.cache_dir={cache_dir}"])
    labels, names = read_psb_labels(labels_file, mesh.n_faces)
    # the MLflow model on the same mesh, as arrays: the same label names, face for face
    mlflow.set_tracking_uri(tracker.uri)
    model = mlflow.pyfunc.load_model(f"runs:/{run_id}/model")
    out = model.predict({"vertices": mesh.vertices, "faces": mesh.faces}, params={"cache_dir": str(cache_dir)})
    assert list(out.columns) == ["label", "label_raw", "label_name"] and len(out) == mesh.n_faces
    assert list(out["label_name"]) == [names[i] for i in labels]
    # and both are the run's own labelling: its per-mesh accuracy, to the last digit
    predicted = np.array([mesh.label_names.index(n) for n in out["label_name"]])
    assert area_weighted_accuracy(predicted, mesh.labels, mesh.face_areas) == pytest.approx(acc, abs=1e-12)
    names = np.asarray(model.metadata.metadata["meshseg"]["label_names"])
    assert np.array_equal(names[out["label"]], out["label_name"])  # `label` indexes the model's label names


def test_the_model_is_listed_on_its_run_with_a_signature_and_an_example(fold):
    tracker, run, _, _ = fold
    # MLflow finds the logged model behind a run's `model` path in its global tracking uri's store, not the
    # client's (meshseg.predict.download_model): without this the test passed only after the one above
    mlflow.set_tracking_uri(tracker.uri)
    run_id = run.info.run_id
    (output,) = tracker.client.get_run(run_id).outputs.model_outputs  # the run's Logged models
    model = tracker.client.get_logged_model(output.model_id)
    assert (model.name, model.source_run_id) == ("model", run_id)
    assert model.tags["config_hash"] == run.data.tags["config_hash"]
    assert {m.key: m.value for m in model.metrics}[FoldRecord.ACC] == run.data.metrics[FoldRecord.ACC]
    # one `model` only: the run keeps no model/ artifact of its own that runs:/<id>/model would mix in
    run_files = {p.name for p in Path(tracker.client.download_artifacts(run_id, "")).iterdir()}
    assert "model" not in run_files and {FoldRecord.PER_MESH, FoldRecord.PREDICTIONS} <= run_files
    folder = Path(tracker.client.download_artifacts(run_id, "model"))
    info = yaml.safe_load((folder / "MLmodel").read_text())
    assert info["model_id"] == model.model_id and "python_function" in info["flavors"]
    inputs = json.loads(info["signature"]["inputs"])
    assert [(i["name"], i["tensor-spec"]["dtype"]) for i in inputs] == [("vertices", "float64"), ("faces", "int64")]
    example = json.loads((folder / "input_example.json").read_text())
    assert len(example["faces"]) == 80 and len(example["vertices"]) == 42  # a small ellipsoid
    serving = json.loads((folder / "serving_input_example.json").read_text())
    assert serving["inputs"] == example  # what `mlflow models serve` takes
    # its requirements are written down, each pinned (nothing to infer, nothing to resolve at load)
    requirements = (folder / "requirements.txt").read_text().split()
    assert "torch==2.13.0" in requirements and all("==" in r for r in requirements)
    assert (folder / "artifacts" / "fold_model" / "model.pt").is_file()


def test_meshseg_predict_reads_a_model_artifact_of_a_run_from_before_logged_models(fold, cache_dir, tmp_path):
    """Runs made before logged models kept the model's files as their `model/` artifact (results/ records and older
    stores have such runs): meshseg.predict loads those as before."""
    from meshseg.predict import FoldModel, load_run_model

    tracker, run, mesh, acc = fold
    new, _ = load_run_model(tracker, run.info.run_id)
    old_store = Tracker(f"sqlite:///{tmp_path}/old/mlflow.db", "meshseg")
    old = old_store.client.create_run(old_store.experiment_id, run_name="a run from before logged models")
    new.save(tmp_path / "files")
    old_store.client.log_artifacts(old.info.run_id, str(tmp_path / "files"), FoldRecord.MODEL)
    model, _ = load_run_model(old_store, old.info.run_id)
    assert isinstance(model, FoldModel) and model.about == new.about
    labels = model.predict(mesh, cache_dir)[2]
    assert area_weighted_accuracy(labels, mesh.labels, mesh.face_areas) == pytest.approx(acc, abs=1e-12)


def test_a_bad_mesh_is_the_callers_error_with_its_reason(fold, cache_dir):
    """Issue 48, 10: MLflow's scoring server passed a bad mesh on as its generic message, the reason buried in
    a stack trace; an MlflowException with an invalid-parameter code is answered 400 with the message itself."""
    from mlflow.exceptions import MlflowException

    tracker, run, mesh, _ = fold
    mlflow.set_tracking_uri(tracker.uri)
    model = mlflow.pyfunc.load_model(f"runs:/{run.info.run_id}/model")
    bad = mesh.faces.copy()
    bad[0, 2] = len(mesh.vertices) + 5
    with pytest.raises(MlflowException) as e:
        model.predict({"vertices": mesh.vertices, "faces": bad}, params={"cache_dir": str(cache_dir)})
    assert e.value.error_code == "INVALID_PARAMETER_VALUE" and e.value.get_http_status_code() == 400
    assert e.value.message.startswith("the model input: ") and "vert" in e.value.message
