"""meshseg on a real one-node SLURM cluster logging to an MLflow server on PostgreSQL (`make cluster-test`,
not part of `make test`): scripts/local_cluster.sh brings munge, slurmdbd, slurmctld, slurmd, PostgreSQL
and `mlflow server` up for this module and down after it.

One story, in order: the features as one SLURM job per category; a budget=smoke sweep of 2 categories x
5 folds through hydra/launcher=slurm makes 10 FINISHED runs on the server, their artifacts downloadable
over HTTP; the same sweep again runs nothing; a job of a third sweep is `scancel`led mid-run, its run ends
KILLED and a rerun completes the fold; the server is restarted mid-sweep and a rerun leaves exactly one
FINISHED run per fold; a report is built from the server."""

import csv
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO, SYSTEM_TEMP
from mlflow import MlflowClient

from meshseg.tracking import is_fold_run

pytestmark = pytest.mark.cluster

SCRIPT = REPO / "scripts/local_cluster.sh"
SMOKE = ["dataset.meshes_per_category=5", "features.groups=[curvature,pca,gc]", "features.name=local", "budget=smoke"]
SLURM = [
    "hydra/launcher=slurm",
    "hydra.launcher.cpus_per_task=1",
    "hydra.launcher.mem_gb=2",
    "hydra.launcher.timeout_min=20",
    "trainer.threads=1",
    "workers=1",
]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """The local cluster, up for this module: its environment (SLURM_CONF, MESHSEG_CLUSTER_URI, ...)."""
    if os.geteuid() != 0:
        pytest.fail("make cluster-test runs as root: it starts munged, slurmd and PostgreSQL")
    state = tmp_path_factory.mktemp("cluster")
    # the daemons' own users (munge, mysql, postgres) must reach their folders and temporary files: not under
    # pytest's 0700 tmp, where conftest points tempfile and TMPDIR for the session
    daemons = Path(tempfile.mkdtemp(prefix="meshseg-cluster-", dir=SYSTEM_TEMP))
    daemons.chmod(0o755)
    env = {**os.environ, "TMPDIR": SYSTEM_TEMP, "MESHSEG_CLUSTER_DIR": str(daemons), "MESHSEG_PYTHON": sys.executable}
    up = subprocess.run(["bash", SCRIPT, "up"], env=env, capture_output=True, text=True, timeout=600)
    try:
        assert up.returncode == 0, up.stderr[-3000:]
        exports = (daemons / "env.sh").read_text().split("export ")[1:]
        env.update(line.strip().split("=", 1) for line in exports)
        env.update(
            MESHSEG_CACHE_DIR=str(state / "cache"),
            MESHSEG_LOG_DIR=str(state / "logs"),
            MESHSEG_MLFLOW_DIR=str(state / "unused-local-store"),
            MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR="false",
        )
        yield env
    finally:
        down = subprocess.run(["bash", SCRIPT, "down"], env=env, capture_output=True, text=True, timeout=300)
        assert down.returncode == 0, down.stderr[-3000:]


def sweep(env, *overrides, wait=True):
    args = [sys.executable, "-m", "meshseg.run", *SMOKE, *SLURM, f"tracking.uri={env['MESHSEG_CLUSTER_URI']}"]
    args += [*overrides, "-m"]
    if not wait:
        return subprocess.Popen(args, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=900)


def server_runs(env, status=None, **tags):
    client = MlflowClient(env["MESHSEG_CLUSTER_URI"])
    exp = client.get_experiment_by_name("meshseg")
    if exp is None:
        return []
    filt = " and ".join(f"tags.{k} = '{v}'" for k, v in tags.items())
    found = [r for r in client.search_runs([exp.experiment_id], filt) if is_fold_run(r)]  # no sweep's parent
    return [r for r in found if status is None or r.info.status == status]


def wait_queue_empty(env, timeout=300):
    deadline = time.time() + timeout
    while subprocess.run(["squeue", "-h"], env=env, capture_output=True, text=True).stdout.strip():
        assert time.time() < deadline, "SLURM jobs still queued"
        time.sleep(1)


def test_sweeps_on_slurm_log_to_the_server_resume_and_survive_scancel(cluster, tmp_path, monkeypatch):
    env, client = cluster, MlflowClient(cluster["MESHSEG_CLUSTER_URI"])
    monkeypatch.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")

    # 0. the features first, one SLURM job per category, into the shared cache
    t0 = time.time()
    args = [sys.executable, "-m", "meshseg.features", *SMOKE[:3], "category=cup,table", *SLURM[:4], "workers=1", "-m"]
    r = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    cache = Path(env["MESHSEG_CACHE_DIR"]) / "features"
    assert {g: len(list((cache / g).glob("*.npz"))) for g in ("curvature", "pca", "gc")} == dict.fromkeys(
        ("curvature", "pca", "gc"), 10
    )
    print(f"features: 2 category jobs in {time.time() - t0:.0f} s")

    # 1. one job per fold through SLURM, every run on the PostgreSQL-backed server with its artifacts
    t0 = time.time()
    r = sweep(env, "category=cup,table")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    done = server_runs(env, "FINISHED")
    assert len(done) == 10 and {(d.data.tags["category"], d.data.tags["fold"]) for d in done} == {
        (c, str(f)) for c in ("cup", "table") for f in range(5)
    }
    assert all(d.data.tags.get("slurm_job") for d in done)  # each ran as a SLURM job, and says which
    assert len({d.data.tags["slurm_job"] for d in done}) == 10
    # the sweep is one parent run, made where the sweep was expanded; each job's run is nested under it and
    # keeps its model as a logged model on the server
    exp_id = client.get_experiment_by_name("meshseg").experiment_id
    (parent,) = [r for r in client.search_runs([exp_id]) if not is_fold_run(r)]
    assert {d.data.tags["mlflow.parentRunId"] for d in done} == {parent.info.run_id}
    models = client.search_logged_models([exp_id])
    assert sorted(m.source_run_id for m in models) == sorted(d.info.run_id for d in done)
    for d in done:
        rows = list(csv.DictReader(open(client.download_artifacts(d.info.run_id, "per_mesh.csv", str(tmp_path)))))
        assert len(rows) == 1 and float(rows[0]["acc"]) == pytest.approx(d.data.metrics["test/acc"])
    print(f"sweep 1: 10 folds in {time.time() - t0:.0f} s")

    # 2. the same sweep again: every fold is skipped, nothing new on the server
    r = sweep(env, "category=cup,table")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert len(server_runs(env)) == 10

    # 3. scancel a job of a third sweep mid-run: its run ends KILLED, the rerun completes the fold
    third = ["category=cup", "seed=1"]
    proc = sweep(env, *third, wait=False)
    deadline = time.time() + 600
    while not (running := server_runs(env, "RUNNING", seed="1")):
        assert proc.poll() is None and time.time() < deadline, "no job of the third sweep started"
        time.sleep(0.5)
    victim = running[0]
    subprocess.run(["scancel", victim.data.tags["slurm_job"]], env=env, check=True)
    out = proc.communicate(timeout=600)[0]
    assert proc.returncode != 0 and "cluster job ended without a result" in out, out[-3000:]
    wait_queue_empty(env)
    killed = client.get_run(victim.info.run_id)
    assert killed.info.status == "KILLED" and "test/acc" not in killed.data.metrics
    r = sweep(env, *third)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    wait_queue_empty(env)
    assert len(server_runs(env, "FINISHED", seed="1")) == 5
    refold = server_runs(env, "FINISHED", seed="1", fold=victim.data.tags["fold"])
    assert len(refold) == 1 and refold[0].data.tags["slurm_job"] != victim.data.tags["slurm_job"]

    # 4. the server restarted mid-sweep: whatever a job could not log, the rerun redoes; nothing counts twice
    fourth = ["category=table", "seed=1"]
    proc = sweep(env, *fourth, wait=False)
    deadline = time.time() + 600
    while not server_runs(env, "RUNNING", seed="1", category="table"):
        assert proc.poll() is None and time.time() < deadline, "no job of the fourth sweep started"
        time.sleep(0.5)
    t0 = time.time()
    r = subprocess.run(["bash", SCRIPT, "restart-mlflow"], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    print(f"server down and up again in {time.time() - t0:.0f} s; first sweep: exit {proc.wait(timeout=900)}")
    wait_queue_empty(env)
    r = sweep(env, *fourth)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    wait_queue_empty(env)
    finished = server_runs(env, "FINISHED", seed="1", category="table")
    assert sorted(int(x.data.tags["fold"]) for x in finished) == [0, 1, 2, 3, 4]
    assert server_runs(env, "RUNNING") == []

    # 5. a report from the server: each cell the mean of its runs' per-mesh accuracies
    manifest = tmp_path / "cluster.yaml"
    manifest.write_text(
        yaml.safe_dump(
            {
                "name": "cluster",
                "title": "smoke sweep on SLURM",
                "overrides": ["dataset=synthetic", "split=5fold"],
                "columns": [{"key": "3B", "label": "1D CNN 3B", "overrides": ["model=cnn1d", "branches=3"]}],
                "groups": [
                    {
                        "name": "synthetic",
                        "sets": [
                            {"name": "Cup", "category": "cup", "published": [None]},
                            {"name": "Table", "category": "table", "published": [None]},
                        ],
                    }
                ],
            }
        )
    )
    args = [sys.executable, "-m", "meshseg.report", str(manifest), *SMOKE, "trainer.threads=1"]
    args += [f"tracking.uri={env['MESHSEG_CLUSTER_URI']}", f"report.out_dir={tmp_path}", "report.results=null"]
    r = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    cells = {row["row"]: row for row in csv.DictReader(open(tmp_path / "cluster/table.csv"))}
    for name, category in (("Cup", "cup"), ("Table", "table")):
        runs = server_runs(env, "FINISHED", category=category, seed="0")
        assert cells[name]["status"] == "ok" and cells[name]["n_meshes"] == "5"
        assert float(cells[name]["reproduced"]) == pytest.approx(
            100 * np.mean([x.data.metrics["test/acc"] for x in runs]), abs=1e-3
        )
    assert Path(tmp_path / "cluster/table.md").read_text().count("| Cup |") == 2  # the table, the refinement block
