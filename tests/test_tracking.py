"""The tracking store under concurrency and bad settings: one-time sqlite initialisation, leases that
keep two sweeps from running one fold twice, store checks at start, and run identity (fold ids)."""

import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time

import pytest
from test_run import SMALL, compose_run, meshseg_run, runs
from test_run import store as store  # noqa: F401  (a fixture)

from meshseg.data.splits import Fold
from meshseg.errors import TrackingError
from meshseg.tracking import (
    LEASE_HEARTBEAT,
    LEASE_OWNER,
    FoldRecord,
    Lease,
    RunKey,
    Tracker,
    fold_identity,
    search_runs,
    store_uri,
)
from meshseg.tracking.store import retry


@pytest.mark.processes
def test_processes_opening_a_new_sqlite_store_at_once_all_succeed(tmp_path):
    """MLflow builds a new sqlite schema on first use; unlocked, a second process doing the same at the
    same moment fails with 'duplicate column name'."""
    start = time.time() + 4  # every process imports first, then all open the store at this instant
    code = textwrap.dedent(f"""
        import time
        from meshseg.tracking import Tracker
        time.sleep(max(0.0, {start} - time.time()))
        t = Tracker("sqlite:///{tmp_path}/mlflow.db", "meshseg")
        print(t.experiment_id)
    """)
    procs = [
        subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for _ in range(3)
    ]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0, 0], [err[-2000:] for _, err in outs]
    assert len({out.strip() for out, _ in outs}) == 1  # one experiment, found by all


def _tracker(tmp_path) -> Tracker:
    return Tracker(f"sqlite:///{tmp_path}/mlflow.db", "meshseg")


def test_a_live_lease_keeps_the_config_and_a_dead_one_is_taken_over(tmp_path):
    t = _tracker(tmp_path)
    tags = {"config_hash": "abc", "fold": 0}
    first, holder = t.claim("fold 0", tags)
    assert first is not None and holder is None
    second, holder = t.claim("fold 0", tags)  # this process holds it, heartbeat fresh: taken
    assert second is None and holder.info.run_id == first
    assert [r.info.run_id for r in t.runs()] == [first]  # the loser's run is deleted, not left RUNNING

    # the same lease held by a process on another host: alive while its heartbeat is fresh ...
    t.client.set_tag(first, LEASE_OWNER, "elsewhere:1")
    assert t.claim("fold 0", tags)[0] is None
    # ... dead once the heartbeat is older than the timeout: the next claim takes over, the old run KILLED
    t.client.set_tag(first, LEASE_HEARTBEAT, f"{time.time() - 600:.0f}")
    third, holder = t.claim("fold 0", tags)
    assert third is not None and holder is None
    old = t.client.get_run(first)
    assert old.info.status == "KILLED" and old.data.tags["superseded_by"] == third


def test_a_lease_of_a_dead_process_on_this_host_is_taken_over_at_once(tmp_path):
    t = _tracker(tmp_path)
    tags = {"config_hash": "abc"}
    first, _ = t.claim("fold 0", tags)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    t.client.set_tag(first, LEASE_OWNER, f"{socket.gethostname()}:{dead.stdout.strip()}")  # heartbeat still fresh
    second, _ = t.claim("fold 0", tags)
    assert second is not None and t.client.get_run(first).info.status == "KILLED"


def test_finished_config_is_never_claimed_and_the_run_beats(tmp_path):
    t = _tracker(tmp_path)
    tags = {"config_hash": "abc"}
    run_id, _ = t.claim("fold 0", tags, Lease(heartbeat_s=0.2, timeout_s=5))
    before = float(t.client.get_run(run_id).data.tags[LEASE_HEARTBEAT])
    with t.run("fold 0", tags, {}, run_id):
        time.sleep(1.5)
        beat = float(t.client.get_run(run_id).data.tags[LEASE_HEARTBEAT])
    assert beat > before  # refreshed while the fold ran
    assert t.client.get_run(run_id).info.status == "FINISHED"
    again, holder = t.claim("fold 0", tags)
    assert again is None and holder.info.status == "FINISHED"


def test_a_claim_stored_later_never_wins_by_an_earlier_start_time(tmp_path, monkeypatch):
    """A client stamps its start time before its run is stored, so a claimant stored after another had
    looked can carry the earlier time; it must still step back (it once won, leaving two holders)."""
    t = _tracker(tmp_path)
    tags = {"config_hash": "abc"}
    first, _ = t.claim("fold 0", tags)
    create = t.client.create_run
    monkeypatch.setattr(t.client, "create_run", lambda *a, **k: create(*a, **{**k, "start_time": 1}))
    second, holder = t.claim("fold 0", tags)
    assert second is None and holder.info.run_id == first
    assert [r.info.run_id for r in t.runs()] == [first]  # the loser's run is gone


def test_claims_racing_from_threads_leave_one_winner(tmp_path):
    t = _tracker(tmp_path)
    got = []
    barrier = threading.Barrier(6)

    def claim():
        barrier.wait()
        got.append(Tracker(t.uri, "meshseg").claim("fold 0", {"config_hash": "race"})[0])

    threads = [threading.Thread(target=claim) for _ in range(6)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    winners = [g for g in got if g is not None]
    assert len(got) == 6 and len(winners) == 1
    assert [r.info.run_id for r in t.runs("attributes.status = 'RUNNING'")] == winners


@pytest.mark.processes
def test_sigterm_mid_run_ends_the_run_killed(store):
    """What `scancel` does to a job: SIGTERM while the fold trains. The run must end KILLED (never stay
    RUNNING or become FINISHED without metrics); a KILLED run does not hold its config, so the next sweep
    trains it again (make cluster-test does that through SLURM)."""
    from conftest import REPO

    store.mkdir(parents=True, exist_ok=True)
    Tracker(f"sqlite:///{store}/mlflow.db", "meshseg", str(store / "artifacts"))  # made first: polls never race it
    args = [sys.executable, "-m", "meshseg.run", *SMALL, "category=cup", "fold=0"]
    proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 300
    while not runs(store, "RUNNING"):
        assert proc.poll() is None and time.time() < deadline, "the run never started"
        time.sleep(0.2)
    proc.terminate()
    out = proc.communicate(timeout=120)[0]
    assert proc.returncode != 0, out[-2000:]
    (killed,) = runs(store)
    assert killed.info.status == "KILLED" and "test/acc" not in killed.data.metrics, out[-2000:]
    assert "SIGTERM received" in out


def test_an_interrupt_waits_for_the_store_call_under_way(tmp_path, monkeypatch):
    """SIGTERM landing inside a store write: raised there, it left sqlite's write transaction open in this
    process, and ending the run KILLED then failed on 'database is locked'. It must come after the call."""
    from meshseg.signals import terminate_interrupts

    t = _tracker(tmp_path)
    run_id = t._create("fold 0", {}).info.run_id
    set_tag, steps = t.client._client.set_tag, []

    def set_tag_hit_by_sigterm(*args):
        os.kill(os.getpid(), signal.SIGTERM)  # its handler runs on this thread at the next bytecode
        steps.append("the write goes on")
        return set_tag(*args)

    monkeypatch.setattr(t.client._client, "set_tag", set_tag_hit_by_sigterm)
    with terminate_interrupts(), pytest.raises(KeyboardInterrupt, match="SIGTERM received"):
        t.client.set_tag(run_id, "k", "v")
    assert steps == ["the write goes on"] and t.client.get_run(run_id).data.tags["k"] == "v"
    t0 = time.perf_counter()
    t._end(None, run_id, "KILLED")  # the store is free at once
    assert t.client.get_run(run_id).info.status == "KILLED" and time.perf_counter() - t0 < 5
    # outside a store call the interrupt is immediate
    with terminate_interrupts(), pytest.raises(KeyboardInterrupt, match="SIGTERM received"):
        os.kill(os.getpid(), signal.SIGTERM)
        steps.append("not reached")
    assert steps == ["the write goes on"]


def test_an_interrupt_during_training_reaches_the_fold_as_an_interrupt():
    """Lightning answers Ctrl-C or SIGTERM in fit() with sys.exit(1), which would end the run FAILED."""
    import numpy as np
    import pytorch_lightning as pl
    import torch

    from meshseg.training.context import TrainContext
    from meshseg.training.data import Standardiser, TrainSet
    from meshseg.training.loop import train_stage

    class InterruptedAtStep3(pl.LightningModule):
        def __init__(self):
            super().__init__()
            self.layer = torch.nn.Linear(4, 2)

        def training_step(self, batch, i):
            if i == 3:
                raise KeyboardInterrupt("SIGTERM received")
            x, y = batch
            return torch.nn.functional.cross_entropy(self.layer(x[:, 0]), y)

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    X = np.random.default_rng(0).normal(size=(64, 1, 4)).astype(np.float32)
    data = TrainSet(X, np.arange(64) % 2, Standardiser().fit(X), 64, 2)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM received"):
        train_stage(InterruptedAtStep3(), data, TrainContext(epochs=2, batch_size=8))


@pytest.mark.processes
def test_two_sweeps_of_one_study_at_once_train_each_fold_once(store):
    """Both sweeps start together; every fold is trained by one of them and skipped by the other."""
    args = [sys.executable, "-m", "meshseg.run", *SMALL, "category=cup", "-m"]
    from conftest import REPO

    procs = [
        subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(2)
    ]
    outs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs[0][-2000:] + outs[1][-2000:]
    done = runs(store, "FINISHED")
    assert sorted(int(r.data.tags["fold"]) for r in done) == [0, 1, 2, 3, 4]
    assert len({r.data.tags["config_hash"] for r in done}) == 5
    assert sum(o.count("skip:") for o in outs) == 5  # each fold skipped by the sweep that did not run it
    assert runs(store, "RUNNING") == []
    # and each sweep wrote its logs to a folder of its own, though both started within one second
    assert len(list((store.parent / "logs" / "multirun").iterdir())) == 2


def test_store_settings_are_checked_at_start(store):
    with pytest.raises(TrackingError, match=r"tracking.uri=garbage://x: unknown store scheme 'garbage'"):
        store_uri("garbage://x")
    r = meshseg_run(*SMALL, "tracking.uri=garbage://x", "-m")
    assert r.returncode == 1 and r.stderr.strip().endswith("'https', 'databricks']") and "Traceback" not in r.stderr

    with socket.socket() as silent:  # accepts connections but never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        uri = f"http://127.0.0.1:{silent.getsockname()[1]}"
        t0 = time.perf_counter()
        r = meshseg_run(*SMALL, f"tracking.uri={uri}", "fold=0", "category=cup")
        took = time.perf_counter() - t0
    assert r.returncode == 1 and f"error: tracking.uri={uri}: no MLflow server answers" in r.stderr, r.stderr[-2000:]
    # well under MLflow's own retries (minutes); the run builds its method (Lightning imported) before it opens
    # the store, which takes a minute on a loaded 2-core machine
    assert "Traceback" not in r.stderr and took < 120


def test_run_identity_is_the_folds_meshes():
    """The same fold index over other meshes (another split file, another dealing) is another run."""
    cfg = compose_run()
    _, h = fold_identity(cfg, "table", Fold(0, ("1", "2", "3"), ("4",)), "data")
    assert h == fold_identity(cfg, "table", Fold(0, ("1", "2", "3"), ("4",)), "data")[1]
    assert h != fold_identity(cfg, "table", Fold(0, ("1", "2", "4"), ("3",)), "data")[1]
    assert h != fold_identity(cfg, "table", Fold(0, ("1", "2"), ("4",)), "data")[1]
    assert h != fold_identity(cfg, "table", Fold(0, ("1", "2", "3"), ("4",)), "other data")[1]
    assert h != fold_identity(cfg, "cup", Fold(0, ("1", "2", "3"), ("4",)), "data")[1]
    moved = compose_run("split=fixed", "split.file=/elsewhere.txt")  # the file's name alone is no knob
    assert (
        fold_identity(moved, "table", Fold(0, ("1",), ("2",)), "d")[1]
        == fold_identity(compose_run("split=fixed"), "table", Fold(0, ("1",), ("2",)), "d")[1]
    )


def test_programming_errors_keep_their_traceback(store, tmp_path):
    """A user error is one line; anything else is a bug and shows where it happened."""
    hook = tmp_path / "sitecustomize.py"  # makes the mesh metric raise a TypeError inside a real run
    hook.write_text(
        "import meshseg.metrics as m\n"
        "def boom(*a, **k):\n    raise TypeError('boom from the metric')\n"
        "m.mesh_scores = boom\n"
    )
    env = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    from conftest import REPO

    r = subprocess.run(
        [sys.executable, "-m", "meshseg.run", *SMALL, "category=cup", "fold=0", "tracking.renders=0"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 1 and "Traceback" in r.stderr and "TypeError: boom from the metric" in r.stderr
    assert "error: boom" not in r.stderr
    (failed,) = runs(store, "FAILED")
    assert "TypeError: boom from the metric" in failed.data.tags["error"]


def test_a_server_that_stops_answering_is_one_tracking_error(monkeypatch):
    """What a job sees when the tracking server goes away mid-sweep: MLflow's own HTTP retries, then one
    TrackingError naming what was being logged (not MLflow's page-long exception)."""
    from mlflow import MlflowClient

    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    client = MlflowClient(f"http://127.0.0.1:{port}")
    with pytest.raises(
        TrackingError, match=r"^log metrics: the tracking server stopped answering \(Connection refused\)"
    ):
        retry(lambda: client.get_experiment_by_name("meshseg"), "log metrics")


def test_two_folds_logging_one_dataset_at_once_both_get_it(tmp_path, monkeypatch):
    """A tracking server looks a dataset up, then inserts it: when two folds of one category log it at the
    same moment, the loser's insert is a unique-key violation (seen on PostgreSQL in CI). Retried, its
    lookup finds the winner's row. The same error elsewhere is not swallowed."""
    from mlflow.exceptions import RestException

    dup = {"error_code": "BAD_REQUEST", "message": 'duplicate key value violates unique constraint "dataset_pk"'}
    tracker = _tracker(tmp_path)
    run_id, other = (tracker.client.create_run(tracker.experiment_id).info.run_id for _ in range(2))
    real, calls = tracker.client.log_inputs, []

    def racing(run_id, inputs):
        calls.append(run_id)
        if len(calls) == 1:
            real(other, inputs)  # the other fold's insert lands first ...
            raise RestException(dup)  # ... and this one's collides with it
        return real(run_id, inputs)

    monkeypatch.setattr(tracker.client, "log_inputs", racing)
    tracker.log_dataset(run_id, "psb/Cup", "835d58916a158212", "LabeledDB_new.tar.xz")
    assert len(calls) == 2
    (got,) = tracker.client.get_run(run_id).inputs.dataset_inputs
    assert (got.dataset.name, got.dataset.digest) == ("psb/Cup", "835d58916a158212")

    def collide():
        raise RestException(dup)

    with pytest.raises(RestException, match="unique constraint"):
        retry(collide, "log metrics")


def test_a_sqlite_store_keeps_its_artifacts_beside_its_database(tmp_path):
    """tracking.uri=sqlite:///X/mlflow.db is all of folder X: runs' and reports' artifacts go to X/artifacts,
    never to ./mlruns of the current folder (an explicit tracking.artifact_dir still wins)."""
    from meshseg.tracking import Tracker

    assert compose_run().tracking.artifact_dir is None
    for experiment in ("meshseg", "meshseg-reports"):
        t = Tracker(f"sqlite:///{tmp_path}/x/mlflow.db", experiment)
        location = t.client.get_experiment(t.experiment_id).artifact_location
        assert location == (tmp_path / "x/artifacts").as_uri()
    elsewhere = Tracker(f"sqlite:///{tmp_path}/y/mlflow.db", "meshseg", str(tmp_path / "elsewhere"))
    assert (
        elsewhere.client.get_experiment(elsewhere.experiment_id).artifact_location == (tmp_path / "elsewhere").as_uri()
    )


def test_search_runs_reads_every_page_and_never_creates_an_experiment(tmp_path, monkeypatch):
    """The report's read of a store: every page of a search (here one run a page), only the runs the filter
    matches, and [] for an experiment the store does not have, which stays absent."""
    from mlflow import MlflowClient

    t = _tracker(tmp_path)
    mine = {t._create(f"fold {i}", {"config_hash": "abc"}).info.run_id for i in range(3)}
    t._create("other", {"config_hash": "xyz"})
    real, pages = MlflowClient.search_runs, []

    def one_a_page(self, experiment_ids, filter_string="", **kwargs):
        pages.append(kwargs.get("page_token"))
        return real(self, experiment_ids, filter_string, **{**kwargs, "max_results": 1})

    monkeypatch.setattr(MlflowClient, "search_runs", one_a_page)
    assert {r.info.run_id for r in search_runs(t.uri, "meshseg", "tags.config_hash = 'abc'")} == mine
    assert len(pages) >= 3 and pages[0] is None and all(pages[1:])  # a page per run, maybe an empty last
    assert {r.info.run_id for r in t.runs("tags.config_hash = 'abc'")} == mine  # Tracker.runs pages alike
    assert len(search_runs(t.uri, "meshseg")) == 4
    assert search_runs(t.uri, "nothing here") == []
    assert MlflowClient(t.uri).get_experiment_by_name("nothing here") is None


def test_a_run_key_names_the_run_and_reads_back_from_its_tags():
    key = RunKey("psb", "Glasses", "cnn1d", 3, "f800", "5fold", 2, "graphcut_agd", "cpu", "abc", "d")
    assert key.name == "Glasses f2 · cnn1d 3B f800 · 5fold · cpu"
    tags = {k: str(v) for k, v in vars(key).items()} | {"git_sha": "x"}
    assert RunKey.from_tags(tags) == key and key.seed == 0
    again = RunKey.from_tags(tags | {"seed": "2"})  # the same fold at another training seed
    assert again.seed == 2 and again.name == "Glasses f2 · cnn1d 3B f800 · 5fold · cpu · seed 2"
    assert set(vars(key)) == set(FoldRecord.TAGS) - {"git_sha"}  # the key is the tags a report selects by


def test_the_machine_tag_names_the_vector_instructions_and_bf16(monkeypatch):
    """Two hosts both called 'AMD EPYC, 2 cores' trained ToG15 3x apart per face; the tag tells them apart by
    what PyTorch's kernels use, and says bf16 only where the CPU announces it."""
    import torch

    from meshseg.tracking import provenance
    from meshseg.tracking.provenance import machine
    from meshseg.training import context

    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX2")
    monkeypatch.setattr(context, "cpu_bf16_flags", lambda: [])
    monkeypatch.setattr(provenance, "blas_kernels", lambda: None)
    assert machine().endswith(" cores, AVX2")
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX512")
    monkeypatch.setattr(context, "cpu_bf16_flags", lambda: ["avx512_bf16"])
    monkeypatch.setattr(provenance, "blas_kernels", lambda: "SkylakeX")
    assert machine().endswith(" cores, AVX512 + bf16, OpenBLAS SkylakeX")


def test_the_blas_kernels_are_those_openblas_reports():
    """What the machine tag names is threadpoolctl's view of numpy's OpenBLAS (OPENBLAS_CORETYPE moves it)."""
    import subprocess
    import sys

    code = "from meshseg.tracking.provenance import blas_kernels; print(blas_kernels())"
    env = {**os.environ, "OPENBLAS_CORETYPE": "Haswell"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "Haswell"


def test_git_sha_is_dirty_for_changed_code_not_for_rewritten_reports(tmp_path):
    # a run worktree's `meshseg.reproduce` rewrites reports/: its later runs still ran the commit's code
    from meshseg.tracking.provenance import git_sha

    def git(*args):
        subprocess.run(["git", "-c", "user.email=t@t", "-c", "user.name=t", *args], cwd=tmp_path, check=True)

    (tmp_path / "meshseg").mkdir()
    (tmp_path / "reports").mkdir()
    (tmp_path / "meshseg" / "a.py").write_text("x = 1\n")
    (tmp_path / "reports" / "t.md").write_text("| 1 |\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "c")
    sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, capture_output=True, text=True).stdout.strip()
    assert git_sha(tmp_path) == sha
    (tmp_path / "reports" / "t.md").write_text("| 2 |\n")
    (tmp_path / "new.py").write_text("")  # untracked: not the commit's, not counted either
    assert git_sha(tmp_path) == sha
    (tmp_path / "meshseg" / "a.py").write_text("x = 2\n")
    assert git_sha(tmp_path) == sha + "+dirty"
    assert git_sha(tmp_path / "missing") == "unknown"


def test_the_per_mesh_table_reads_back_typed_in_its_column_order(tmp_path):
    from meshseg.tracking import FoldRecord

    rows = [{"acc": 0.5, "mesh": "007", "faces": 12, "area": 1.25, "acc_raw": 0.25}]
    path = tmp_path / FoldRecord.PER_MESH
    path.write_text(FoldRecord.per_mesh_csv(rows))
    assert path.read_text().splitlines() == ["mesh,faces,area,acc_raw,acc", "007,12,1.25,0.25,0.5"]
    (back,) = FoldRecord.read_per_mesh(path)
    assert back == rows[0] and back["mesh"] == "007" and type(back["faces"]) is int  # an id keeps its zeros
