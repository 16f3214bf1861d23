"""docs/adding-a-method.md, executed: its code blocks (a network, a scikit-learn-shaped fitter and their
YAML files) are written to a folder of the test's own, and `meshseg.run` trains both at budget=smoke with
nothing else added. If the page's example stops working, this fails."""

import os
import re
import subprocess
import sys

import numpy as np
from conftest import REPO
from mlflow import MlflowClient

from meshseg.tracking import is_fold_run

SMALL = [
    "dataset.meshes_per_category=5",
    "features.groups=[curvature,pca,gc]",
    "features.name=local",
    "budget=smoke",
    "category=figure",
    "fold=0",
    "tracking.renders=0",
    "trainer.threads=1",
]


def page_files() -> dict[str, str]:
    """The page's code blocks that name a file: {path: text}."""
    text = (REPO / "docs/adding-a-method.md").read_text()
    return dict(re.findall(r"```(?:python|yaml) (\S+)\n(.*?)```", text, re.S))


def test_a_method_is_one_class_and_one_yaml_file(tmp_path, cache_dir):
    files = page_files()
    assert set(files) == {"my_methods.py", "my_conf/model/mlp.yaml", "my_conf/model/nearest_mean.yaml"}
    for path, body in files.items():
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text(body)
    env = {
        **os.environ,
        "PYTHONPATH": str(tmp_path),
        "MESHSEG_CACHE_DIR": str(cache_dir),
        "MESHSEG_MLFLOW_DIR": str(tmp_path / "mlruns"),
        "MESHSEG_LOG_DIR": str(tmp_path / "logs"),
    }
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "meshseg.run",
            "model=mlp,nearest_mean",
            *SMALL,
            f"hydra.searchpath=[file://{tmp_path}/my_conf]",
            "-m",
        ],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]

    client = MlflowClient(f"sqlite:///{tmp_path}/mlruns/mlflow.db")
    found = client.search_runs([client.get_experiment_by_name("meshseg").experiment_id])
    by_model = {run.data.tags["model"]: run for run in found if is_fold_run(run)}  # not the sweep's parent
    assert sorted(by_model) == ["mlp", "nearest_mean"]
    for model, run in by_model.items():
        assert run.info.status == "FINISHED"
        assert run.data.tags["branches"] == ("1" if model == "nearest_mean" else "3")
        # 4 parts of a figure: chance is about 0.25; both methods separate them well (measured 0.93, 0.87)
        assert 0.6 < run.data.metrics["test/acc"] <= 1.0
        config = client.download_artifacts(run.info.run_id, "config.yaml")
        assert "my_methods." in open(config).read()  # the class the YAML named is in the run's identity
    with np.load(client.download_artifacts(by_model["nearest_mean"].info.run_id, "predictions.npz")) as z:
        probs = z["probs_0"].astype(np.float32)
    assert probs.shape[1] == 4 and np.allclose(probs.sum(axis=1), 1, atol=1e-2)
