"""`python -m meshseg.run`: config groups, validation, tracking contract, resume, parallel workers.

Runs use a small synthetic set (5 meshes per category), a cheap feature set, budget=smoke and one torch
thread (the two test workers keep both cores busy), so a run takes seconds; the feature cache is shared by
the whole session.
"""

import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO
from hydra import compose, initialize_config_dir
from mlflow import MlflowClient

from meshseg import CONF_DIR
from meshseg.tracking import FoldRecord, config_hash, flatten, is_fold_run

SMALL = [
    "dataset.meshes_per_category=5",
    "features.groups=[curvature,pca,gc]",
    "features.name=local",
    "budget=smoke",
    "trainer.threads=1",
]


def compose_run(*overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("run", overrides=list(overrides))


@pytest.fixture
def store(tmp_path, cache_dir, monkeypatch):
    """Environment for one test's runs: its own MLflow store and logs, the session's feature cache."""
    env = {
        "MESHSEG_CACHE_DIR": str(cache_dir),
        "MESHSEG_MLFLOW_DIR": str(tmp_path / "mlruns"),
        "MESHSEG_LOG_DIR": str(tmp_path / "logs"),
    }
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    return tmp_path / "mlruns"


def meshseg_run(*overrides, timeout=600, **kw):
    return subprocess.run(
        [sys.executable, "-m", "meshseg.run", *overrides],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=os.environ.copy(),
        **kw,
    )


def runs(store: Path, status: str | None = None):
    """The store's fold runs (a sweep's parent run is none: tests/test_sweep_parent.py)."""
    client = MlflowClient(f"sqlite:///{store}/mlflow.db")
    exp = client.get_experiment_by_name("meshseg")
    found = client.search_runs([exp.experiment_id]) if exp else []
    return [r for r in found if is_fold_run(r) and (status is None or r.info.status == status)]


# --- configuration --------------------------------------------------------------------------------

GROUPS = {
    "dataset": ["synthetic", "psb", "coseg"],
    "features": ["f800", "f600", "cf0", "cf1", "cf0_1", "cf1_5", "cf0_5"],
    "model": ["cnn1d", "cnn1d_reference", "cnn2d", "pca_nn", "ae_nn", "ae_rf", "rf"],
    "split": ["loo", "5fold", "fixed"],
    "refine": ["none", "graphcut_classic", "graphcut_agd"],
    "budget": ["smoke", "demo", "cpu", "paper"],
    "trainer": ["cpu", "gpu"],
    "tracking": ["mlflow"],
}


@pytest.mark.parametrize("group, option", [(g, o) for g, opts in GROUPS.items() for o in opts])
def test_every_group_option_composes(group, option):
    cfg = compose_run(f"{group}={option}")
    node = cfg[group]
    if group == "budget":
        assert node.name == option and node.epochs >= 1
    elif group == "features":
        assert node.name == option
    elif group in ("model", "refine"):
        assert node.name == option
    elif group == "trainer":
        assert node.accelerator == option
    single_scale = group == "model" and option not in ("cnn1d", "cnn1d_reference")  # the baselines fix branches: 1
    assert cfg.branches == (1 if single_scale else 3) and cfg.seed == 0 and cfg.category is None and cfg.fold is None
    assert cfg.refine.name == (option if group == "refine" else "graphcut_agd")  # the paper's refinement by default


@pytest.mark.parametrize("dataset, budget", [("synthetic", "demo"), ("psb", "cpu"), ("coseg", "cpu")])
def test_each_dataset_brings_its_default_budget(dataset, budget):
    assert compose_run(f"dataset={dataset}").budget.name == budget
    assert compose_run(f"dataset={dataset}", "budget=smoke").budget.name == "smoke"


def test_paper_budget_is_every_face_for_50_epochs():
    b = compose_run("budget=paper").budget
    assert b.faces_per_mesh is None and b.epochs == 50


def test_model_is_the_papers_1d_cnn():
    m = compose_run().model
    assert (list(m.net.channels), list(m.net.kernels), m.net.hidden) == ([16, 32], [15, 11], 172)
    assert (m.net.negative_slope, m.net.dropout, m.optim.momentum) == (0.2, 0.5, 0.9)
    assert (m.optim.lr_start, m.optim.lr_end) == (1e-2, 1e-4)


def test_bad_values_fail_at_once_listing_what_is_allowed(store):
    r = meshseg_run("branches=5", *SMALL)
    assert r.returncode == 1 and "error: branches=5 is not allowed: choose one of [1, 2, 3, 4]" in r.stderr
    r = meshseg_run("category=chair", *SMALL, "-m")  # sweeps are checked before any job starts
    assert r.returncode == 1 and "has no category 'chair'; it has ['table', 'cup', 'figure']" in r.stderr
    assert not (store / "mlflow.db").exists() or runs(store) == []
    r = meshseg_run("model=transformer", *SMALL)
    assert r.returncode == 1 and "Could not find 'model/transformer'" in r.stderr and "cnn1d" in r.stderr
    r = meshseg_run("fold=9", *SMALL)
    assert r.returncode == 1 and "error: fold=9 is out of range: split 5fold of table has folds 0..4" in r.stderr


@pytest.mark.parametrize(
    "override, message",
    [
        ("branches=5", "error: branches=5 is not allowed: choose one of [1, 2, 3, 4]"),
        ("fold=9", "error: fold=9 is out of range: split 5fold of table has folds 0..4"),
        ("category=chair", "has no category 'chair'; it has ['table', 'cup', 'figure']"),
        ("budget.epochs=0", "error: budget.epochs=0 is not allowed (budget smoke): it must be an integer >= 1"),
        ("budget.batch_size=abc", "error: budget.batch_size=abc is not allowed (budget smoke): it must be an integer"),
        # issue 48, 5: "abc" was a traceback, 64.5 passed the check and failed the run after its features,
        # 1e12 trained on every face under a config hash of its own
        ("budget.faces_per_mesh=abc", "error: budget.faces_per_mesh=abc is not allowed (budget smoke): it must be"),
        ("budget.faces_per_mesh=64.5", "error: budget.faces_per_mesh=64.5 is not allowed (budget smoke): it must"),
        ("budget.faces_per_mesh=1e12", "from 1 to 10,000,000, or null for every face"),
        ("budget.faces_per_mesh=0", "error: budget.faces_per_mesh=0 is not allowed"),
        ("tracking.uri=garbage://x", "error: tracking.uri=garbage://x: unknown store scheme 'garbage'"),
        ("refine.lam=-1", "refine.lam=-1"),
        (
            "budget.resample=sometimes",
            "error: budget.resample=sometimes is not allowed: choose one of ['fold', 'epoch']",
        ),
        (
            "split.seed=-2",
            "error: split.seed=-2 is not allowed: it must be null (meshes dealt by id) or an integer >= 0",
        ),
        ("model=rf budget.resample=epoch", "error: budget.resample=epoch is not allowed with ForestFitter"),
        ("+modle=cnn1d", "error: unknown setting 'modle' (did you mean model?)"),
        ("modle=cnn1d", "error: unknown setting 'modle' (did you mean model?)"),
    ],
)
def test_bad_values_under_m_get_one_line_before_any_work(store, override, message):
    """A sweep checks every job's settings before the first starts: one `error:` line, no traceback,
    nothing in the store (`refine.lam=-1` used to be refused only after the fold had trained)."""
    r = meshseg_run(*SMALL, *override.split(), "-m", timeout=120)
    assert r.returncode == 1 and message in r.stderr, r.stderr[-2000:]
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (store / "mlflow.db").exists() or runs(store) == []


def test_console_scripts_and_hydra_tab_completion():
    """`meshseg-run` is the same app as `python -m meshseg.run`, and Hydra's shell completion works through
    it: `-sc install=bash` is a flag and its value, not a setting to refuse."""
    bin_dir = Path(sys.executable).parent
    for name in ("meshseg-run", "meshseg-report", "meshseg-reproduce", "meshseg-results", "meshseg-features"):
        assert (bin_dir / name).is_file(), f"{name} not installed (pyproject [project.scripts]; make install)"
    typo = subprocess.run([bin_dir / "meshseg-run", "modle=cnn1d"], capture_output=True, text=True, timeout=120)
    assert typo.returncode == 1 and typo.stderr.startswith("error: unknown setting 'modle' (did you mean model?)")
    sc = subprocess.run([bin_dir / "meshseg-run", "-sc", "install=bash"], capture_output=True, text=True, timeout=120)
    assert sc.returncode == 0 and "hydra_bash_completion" in sc.stdout and "meshseg-run" in sc.stdout, sc.stderr
    env = {**os.environ, "COMP_LINE": "meshseg-run model=", "COMP_POINT": "18"}  # what bash asks on <TAB>
    query = [bin_dir / "meshseg-run", "-sc", "query=bash"]
    options = subprocess.run(query, capture_output=True, text=True, timeout=120, env=env).stdout.split()
    assert {"model=cnn1d", "model=cnn2d", "model=rf"} <= set(options), options


def test_trainer_threads_bounds_numpys_blas_pool_as_well_as_torchs():
    """Two workers at trainer.threads=1 on two cores: a BLAS pool of every core spins for a core the other
    holds (PCA & NN's principal axes 13.6x slower, benchmarks/blas_threads.py)."""
    import torch
    from omegaconf import OmegaConf
    from threadpoolctl import threadpool_info, threadpool_limits

    from meshseg.run import setup_process

    before = torch.get_num_threads()
    with threadpool_limits(limits=None):  # restores every pool's count afterwards
        setup_process(OmegaConf.create({"threads": 1, "malloc_tune": False}))
        blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
        assert blas and all(p["num_threads"] == 1 for p in blas), blas
        assert torch.get_num_threads() == 1
    torch.set_num_threads(before)


def test_config_hash_ignores_paths_and_sees_knobs():
    cfg = {"paths": {"cache_dir": "a"}, "branches": 3, "model": {"hidden": 172}}
    h = config_hash(cfg, ["paths"], {"data_hash": "x"})
    assert h == config_hash({**cfg, "paths": {"cache_dir": "b"}}, ["paths"], {"data_hash": "x"})
    assert h != config_hash({**cfg, "branches": 2}, ["paths"], {"data_hash": "x"})
    assert h != config_hash(cfg, ["paths"], {"data_hash": "y"})
    assert flatten({"a": {"b": [1, {"c": 2}]}}) == {"a.b.0": 1, "a.b.1.c": 2}


# --- runs ------------------------------------------------------------------------------------------


def test_one_run_follows_the_tracking_contract_and_reruns_skip(store, tmp_path):
    from meshseg.predict import download_model
    from meshseg.tracking import Tracker

    r = meshseg_run(*SMALL, "category=cup", "fold=1")
    assert r.returncode == 0, r.stderr[-3000:]
    (run,) = runs(store)
    assert run.info.status == "FINISHED"
    # no progress bar: one line per epoch (budget=smoke trains 2), with what the module logged
    # MLflow's own fields, which its UI shows: source, user, commit, the command line as the description
    tags = run.data.tags
    assert tags["mlflow.source.name"] == "meshseg.run" and tags["mlflow.source.type"] == "LOCAL"
    assert tags["mlflow.note.content"] == "`python -m meshseg.run " + " ".join([*SMALL, "category=cup", "fold=1"]) + "`"
    assert tags["mlflow.user"] and tags["mlflow.source.git.commit"] == tags["git_sha"].removesuffix("+dirty")
    assert "sweep_id" not in tags  # a single run is no sweep
    out = r.stdout + r.stderr
    epochs = re.findall(r"epoch (\d)/2: train/acc \S+, train/loss \S+, train/lr \S+; \S+ s, about \d+ s left", out)
    assert epochs == ["1", "2"], out[-3000:]
    tags = run.data.tags
    assert set(FoldRecord.TAGS) <= set(tags)
    assert (
        tags["dataset"],
        tags["category"],
        tags["fold"],
        tags["split"],
        tags["budget"],
        tags["model"],
        tags["branches"],
        tags["refine"],
        tags["features"],
    ) == ("synthetic", "cup", "1", "5fold", "smoke", "cnn1d", "3", "graphcut_agd", "local")
    m = run.data.metrics
    assert 0 <= m["test/acc_raw"] <= 1 and 0 <= m["test/acc"] <= 1
    assert 200 < m["memory/peak_rss_mib"] < 8192  # the process holds torch at least; the peak is this run's
    assert run.data.params["budget.epochs"] == "2" and run.data.params["category"] == "cup"
    # the name leads with what differs between a sweep's runs; a list is one param; no tracking settings
    assert run.info.run_name == "cup f1 · cnn1d 3B local · 5fold · smoke"
    assert run.data.params["features.groups"] == '["curvature", "pca", "gc"]'
    assert not [k for k in run.data.params if k.startswith("tracking.") or k.startswith("features.groups.")]
    assert int(run.data.params["n_epochs"]) == 2 and int(run.data.params["n_train_samples"]) > 0
    (inp,) = run.inputs.dataset_inputs
    assert inp.dataset.name == "synthetic/cup" and tags["data_hash"].startswith(inp.dataset.digest)
    assert "meshseg.data.synthetic" in inp.dataset.source
    client = MlflowClient(f"sqlite:///{store}/mlflow.db")
    assert len(client.get_metric_history(run.info.run_id, "train/loss")) == 2  # one point per epoch
    lrs = [h.value for h in client.get_metric_history(run.info.run_id, "train/lr")]
    assert np.allclose(lrs, [1e-2, 1e-4])
    local = Path(client.download_artifacts(run.info.run_id, ""))
    assert sorted(p.name for p in local.iterdir()) == [
        "config.yaml",
        "confusion.png",
        "overrides.yaml",
        "per_mesh.csv",
        "predictions.npz",
        "renders",
        "run.log",
    ]
    # the fold's model: its MLflow logged model (meshseg.pyfunc), the FoldModel's files inside
    model = download_model(Tracker(f"sqlite:///{store}/mlflow.db", "meshseg"), run, str(tmp_path / "m"))
    assert {"MLmodel", "input_example.json"} <= {p.name for p in model.iterdir()}
    assert sorted(p.name for p in (model / "artifacts/fold_model").iterdir()) == ["model.pt", "model.yaml"]
    assert "category=cup" in (local / "overrides.yaml").read_text()
    assert "epoch 2/2" in (local / "run.log").read_text()  # the job's own log, as written by the run
    assert [p.name for p in (local / "renders").iterdir()] == ["mesh_1.png"]  # the fold's one test mesh
    assert (local / "confusion.png").read_bytes()[:4] == b"\x89PNG"
    table = (local / "per_mesh.csv").read_text().splitlines()
    assert table[0] == "mesh,faces,area,acc_raw,acc" and table[1].startswith("1,")  # 5fold: fold 1 tests mesh 1
    assert np.isclose(float(table[1].split(",")[4]), m["test/acc"])
    with np.load(local / "predictions.npz") as z:
        assert z["labels_1"].shape == (int(table[1].split(",")[1]),)
        assert np.allclose(z["probs_1"].astype(np.float32).sum(axis=1), 1, atol=1e-2)

    # refine.lam=2 is the default 2.0 written as an integer: the same config, so the same run
    again = meshseg_run(*SMALL, "category=cup", "fold=1", "refine.lam=2")
    assert again.returncode == 0 and "skip: cup f1 · cnn1d 3B local · 5fold · smoke" in again.stdout + again.stderr
    assert len(runs(store)) == 1


def test_same_seed_twice_gives_identical_results(store, tmp_path):
    from meshseg.run import run

    accs, probs = [], []
    for i in range(2):
        cfg = compose_run(*SMALL, "category=figure", "fold=2", f"paths.mlflow_dir={tmp_path}/store{i}")
        accs.append(run(cfg).acc)
        client = MlflowClient(f"sqlite:///{tmp_path}/store{i}/mlflow.db")
        (r,) = client.search_runs([client.get_experiment_by_name("meshseg").experiment_id])
        with np.load(client.download_artifacts(r.info.run_id, "predictions.npz")) as z:
            probs.append(z["probs_2"])
    assert accs[0] == accs[1]
    assert np.array_equal(probs[0], probs[1])


def test_a_failing_category_is_marked_failed_and_the_others_finish(store, tmp_path):
    """A COSEG-layout root with two sets of two meshes; mesh 1 of `tables` is truncated. Every fold of
    `tables` needs it, so both fail (error text tagged); both folds of `cups` finish; the sweep exits non-zero."""
    from meshseg.data.datasets import Synthetic
    from meshseg.data.io import write_off

    for name, category in [("cups", "cup"), ("tables", "table")]:
        root = tmp_path / "coseg" / name
        (root / "shapes").mkdir(parents=True)
        (root / "gt").mkdir()
        for mesh in Synthetic(categories=[category], meshes_per_category=2, max_faces=4000).meshes(category):
            write_off(root / "shapes" / f"{mesh.id}.off", mesh.vertices, mesh.faces)
            (root / "gt" / f"{mesh.id}.seg").write_text("\n".join(str(v + 1) for v in mesh.labels) + "\n")
    bad = tmp_path / "coseg" / "tables" / "shapes" / "1.off"
    bad.write_text("\n".join(bad.read_text().splitlines()[:-40]) + "\n")
    r = meshseg_run(
        "dataset=coseg",
        f"dataset.root={tmp_path / 'coseg'}",
        "budget=smoke",
        "split.k=2",
        "features.groups=[curvature,pca,gc]",
        "features.name=local",
        "trainer.threads=1",
        "-m",
    )
    assert r.returncode != 0
    done = runs(store)
    assert sorted((x.data.tags["category"], x.data.tags["fold"], x.info.status) for x in done) == [
        ("cups", "0", "FINISHED"),
        ("cups", "1", "FINISHED"),
        ("tables", "0", "FAILED"),
        ("tables", "1", "FAILED"),
    ]
    for failed in runs(store, "FAILED"):
        assert f"{bad}:" in failed.data.tags["error"]


@pytest.mark.processes
def test_a_killed_fold_resumes_from_its_last_epoch_checkpoint(store, cache_dir):
    """tracking.checkpoints=true (what budget=paper does on its own): SIGKILL a fold mid-training; its
    rerun resumes after the last checkpointed epoch, trains only the epochs left, and leaves no checkpoint."""
    args = [*SMALL, "category=cup", "fold=0", "budget.epochs=8", "tracking.checkpoints=true"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "meshseg.run", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},  # each line as it is logged
    )
    seen = []
    try:
        for line in proc.stdout:
            seen.append(line)
            if "epoch 3/8:" in line:
                os.killpg(proc.pid, signal.SIGKILL)
                break
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, "".join(seen)[-3000:]
    (ckpt,) = (cache_dir / "checkpoints").glob("*/net/last.ckpt")
    r = meshseg_run(*args)
    assert r.returncode == 0, r.stderr[-3000:]
    out = r.stdout + r.stderr
    resumed = int(re.search(r"net: resuming from its checkpoint after epoch (\d)/8", out)[1])
    assert resumed >= 2  # epoch 3 was logged before the kill, so epoch 2's checkpoint was written
    assert re.findall(r"epoch (\d)/8:", out) == [str(e) for e in range(resumed + 1, 9)]  # only the epochs left
    (run,) = runs(store, "FINISHED")
    assert run.info.status == "FINISHED" and not ckpt.parent.parent.exists()


@pytest.mark.processes
def test_killed_sweep_resumes_doing_only_what_is_missing(store):
    """SIGKILL a sweep once two folds have FINISHED; rerunning skips those and redoes the rest."""
    args = [sys.executable, "-m", "meshseg.run", *SMALL, "category=table", "-m"]
    proc = subprocess.Popen(
        args, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    db = store / "mlflow.db"
    deadline = time.time() + 300
    finished = 0
    try:
        while time.time() < deadline and proc.poll() is None:
            if db.exists():
                try:
                    with sqlite3.connect(db, timeout=1) as con:
                        finished = con.execute("select count(*) from runs where status = 'FINISHED'").fetchone()[0]
                except sqlite3.OperationalError:
                    finished = 0
                if finished >= 2:
                    os.killpg(proc.pid, signal.SIGKILL)
                    break
            time.sleep(0.05)
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, "the sweep ended before it could be killed"
    before = {r.data.tags["fold"] for r in runs(store, "FINISHED")}
    assert 2 <= len(before) < 5

    r = meshseg_run(*SMALL, "category=table", "-m")
    assert r.returncode == 0, r.stderr[-3000:]
    out = r.stdout + r.stderr
    skipped = re.findall(r"skip: table f(\d) · cnn1d 3B local", out)
    assert sorted(before) == sorted(skipped)
    # progress: each job says where the sweep is; the sweep ends with what it did and the accuracy so far
    jobs = re.findall(r"job (\d)/5 \([^)]*?(, about \d+ (?:s|min) left)?\)", out)
    assert [k for k, _ in jobs] == ["1", "2", "3", "4", "5"]
    # the time left is paced by the jobs that ran: none before the first fold this sweep trains
    first_run = min({"0", "1", "2", "3", "4"} - set(before))
    assert [bool(left) for _, left in jobs] == [k > int(first_run) for k in range(5)]
    n = len(before)
    assert f"sweep: {5 - n} ran, {n} skipped, 0 failed in " in out
    accs = [100 * x.data.metrics["test/acc"] for x in runs(store, "FINISHED")]
    assert f"sweep: mean test/acc by category (fold means, %): table {np.mean(accs):.2f} (5 folds)" in out
    finished = runs(store, "FINISHED")
    assert sorted(int(x.data.tags["fold"]) for x in finished) == [0, 1, 2, 3, 4]
    assert runs(store, "RUNNING") == []  # a run killed mid-way is marked KILLED once redone
    # each sweep's runs carry its id: the first sweep's survivors one, the resumed folds another
    first = {x.data.tags["sweep_id"] for x in finished if x.data.tags["fold"] in before}
    resumed = {x.data.tags["sweep_id"] for x in finished if x.data.tags["fold"] not in before}
    assert len(first) == len(resumed) == 1 and first != resumed
    rerun = meshseg_run(*SMALL, "category=table", "-m")
    assert (rerun.stdout + rerun.stderr).count("skip:") == 5 and len(runs(store, "FINISHED")) == 5


@pytest.mark.processes
def test_two_joblib_workers_share_one_sqlite_store(store):
    r = meshseg_run(
        *SMALL,
        "category=cup",
        "fold=0,2",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        "-m",
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "locked" not in r.stderr
    done = runs(store, "FINISHED")
    assert sorted(x.data.tags["fold"] for x in done) == ["0", "2"]
