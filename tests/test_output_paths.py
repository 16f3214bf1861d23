"""Output paths and a few messages (issue 26, defects 5 and 7): every bad output path is one `error:` line
before any work, nothing half-written, no store created by a mistyped path."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO
from mlflow import MlflowClient

from meshseg.data.io import check_output_file, check_output_folder, write_off
from meshseg.errors import ConfigError

READ_ONLY = Path("/proc/meshseg-no-such-file")  # /proc takes no new file, even from root


def cli(module: str, *args, env=None, timeout=300):
    env = {**os.environ, **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", module, *map(str, args)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )


def one_error_line(r, text: str):
    assert r.returncode != 0, r.stdout[-500:]
    lines = r.stderr.strip().splitlines()
    assert lines and lines[-1].startswith("error: ") and text in lines[-1], r.stderr[-2000:]
    assert "Traceback" not in r.stderr


def test_output_file_and_folder_checks(tmp_path):
    (tmp_path / "a_file").write_text("x")
    cases = [
        (tmp_path, "out=.* is a folder; name the file to write"),
        (tmp_path / "missing/labels.txt", "its folder .*missing does not exist"),
        (tmp_path / "a_file/labels.txt", "a_file is a file, not a folder"),
        (READ_ONLY, "cannot write in /proc"),
    ]
    for path, message in cases:
        with pytest.raises(ConfigError, match=message):
            check_output_file(path, "out")
    assert check_output_file(tmp_path / "labels.txt", "out") == tmp_path / "labels.txt"
    with pytest.raises(ConfigError, match="out=.*a_file is a file; it must be a folder"):
        check_output_folder(tmp_path / "a_file", "out")
    with pytest.raises(ConfigError, match="a_file is a file, not a folder"):
        check_output_folder(tmp_path / "a_file/x/y", "out")
    with pytest.raises(ConfigError, match="cannot write in /proc"):
        check_output_folder(Path("/proc/meshseg/x"), "out")
    assert check_output_folder(tmp_path / "new/deeper", "out") == tmp_path / "new/deeper"
    assert not (tmp_path / "new").exists()  # checked, not made
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]  # the probes left nothing


def test_predict_checks_its_outputs_and_store_before_any_work(tmp_path):
    mesh = tmp_path / "tet.off"
    write_off(mesh, np.eye(4, 3), np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]))
    store = tmp_path / "store/mlflow.db"
    store.parent.mkdir()
    MlflowClient(f"sqlite:///{store}").search_experiments()  # an existing (empty) store
    uri = f"tracking.uri=sqlite:///{store}"
    (tmp_path / "a_file").write_text("x")
    for out, message in [
        (tmp_path / "missing/x.txt", "out=" + str(tmp_path / "missing/x.txt") + ": its folder"),
        (tmp_path, "is a folder; name the file to write"),
        (tmp_path / "a_file/x.txt", "is a file, not a folder"),
        (READ_ONLY, "cannot write in /proc"),
    ]:
        one_error_line(cli("meshseg.predict", "run_id=0123456789abcdef", f"mesh={mesh}", f"out={out}", uri), message)
    # render= in a missing folder: refused before the labels file is written
    out = tmp_path / "labels.txt"
    r = cli(
        "meshseg.predict", "run_id=0123456789abcdef", f"mesh={mesh}", f"out={out}", f"render={tmp_path}/no/x.png", uri
    )
    one_error_line(r, "render=")
    assert not out.exists()
    # a mistyped store is one line, and no empty store is left behind
    typo = tmp_path / "stor/mlflow.db"
    r = cli(
        "meshseg.predict", "run_id=0123456789abcdef", f"mesh={mesh}", f"out={out}", f"tracking.uri=sqlite:///{typo}"
    )
    one_error_line(r, "no such store")
    assert not typo.exists() and not typo.parent.exists()


def test_results_commands_say_what_is_wrong_before_opening_a_store(tmp_path):
    (tmp_path / "a_file").write_text("x")
    store = tmp_path / "new/mlflow.db"
    uri = f"tracking.uri=sqlite:///{store}"
    r = cli("meshseg.results", "exprot")
    assert r.returncode == 1 and r.stderr.startswith("error: unknown action 'exprot': choose export, import or verify")
    one_error_line(
        cli("meshseg.results", "export", f"out={tmp_path / 'a_file'}", uri), "is a file; it must be a folder"
    )
    one_error_line(cli("meshseg.results", "import", f"dir={tmp_path / 'nowhere'}", uri), "no such folder of results")
    assert not store.exists() and not store.parent.exists()


def test_report_refuses_a_file_as_out_dir_and_a_missing_results_folder(tmp_path):
    (tmp_path / "a_file").write_text("x")
    env = {"MESHSEG_MLFLOW_DIR": str(tmp_path / "store"), "MESHSEG_LOG_DIR": str(tmp_path / "logs")}
    synth = "experiments/synthetic.yaml"
    r = cli("meshseg.report", synth, f"report.out_dir={tmp_path / 'a_file'}", env=env)
    one_error_line(r, "report.out_dir=" + str(tmp_path / "a_file") + " is a file")
    r = cli("meshseg.report", synth, f"report.results={tmp_path / 'nowhere'}", env=env)
    one_error_line(r, "no such folder of results records")
    assert not (tmp_path / "store").exists()


def test_features_refuses_an_unwritable_out_before_computing(tmp_path):
    mesh = tmp_path / "tet.off"
    write_off(mesh, np.eye(4, 3), np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]))
    r = cli("meshseg.features", f"mesh={mesh}", "out=/proc/meshseg/x.npy", "cache=false")
    one_error_line(r, "cannot write in /proc")


def test_a_truncated_model_names_the_run_not_a_temporary_download(smoke_store, monkeypatch):
    import meshseg.predict
    from meshseg.predict import load_run_model
    from meshseg.tracking import Tracker

    tracker = Tracker(f"sqlite:///{smoke_store}/mlflow.db", "meshseg", str(Path(smoke_store) / "artifacts"))
    run = tracker.runs("tags.model = 'cnn1d'")[0]
    download = meshseg.predict.download_model

    def truncating(*args):  # downloads as the store does, then cuts model.pt short (the store itself is shared)
        (model,) = (folder := download(*args)).rglob("model.pt")
        model.write_bytes(model.read_bytes()[:100])
        return folder

    monkeypatch.setattr(meshseg.predict, "download_model", truncating)
    with pytest.raises(Exception, match=rf"^run_id={run.info.run_id} \(.*\): its model cannot load") as e:
        load_run_model(tracker, run.info.run_id)
    assert "/tmp" not in str(e.value)  # not the temporary download's path, gone by the time it is read
