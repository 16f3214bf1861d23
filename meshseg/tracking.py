"""MLflow under the tracking contract (DESIGN "Tracking contract"): one run per (method config,
dataset, category, split, fold), tagged with every knob the report needs; params are the flattened
resolved config; artifacts are the config, a per-mesh table, the per-face predictions and pictures
(renders of test meshes, predicted beside ground truth, and the confusion matrix).

A run's identity is `config_hash`: a config whose hash already has a FINISHED run is not run again,
so an interrupted sweep, rerun, does only what is missing. A run that raises ends FAILED with its
error text in the `error` tag; one interrupted from the keyboard ends KILLED; one killed outright
stays RUNNING and is marked KILLED when a later run of the same hash finishes.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import logging
import random
import subprocess
import tempfile
import threading
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from meshseg.errors import TrackingError

log = logging.getLogger(__name__)


class FoldRecord:
    """What one fold's run records, defined once: `meshseg.run` writes it; the report, `reproduce` and
    the notebooks read it by these names."""

    #: tags every fold run carries (the report selects runs by these)
    TAGS = (
        "dataset",
        "category",
        "model",
        "branches",
        "features",
        "split",
        "fold",
        "refine",
        "budget",
        "config_hash",
        "git_sha",
        "data_hash",
    )
    #: the two accuracies every fold logs (area-weighted mean over the test meshes), after and before refinement.
    #: Metrics are named by role: train/* (per epoch, from Lightning), test/*, time/<phase>_s, speed/*;
    #: counts (samples, faces, epochs) are params n_*.
    ACC, ACC_RAW = "test/acc", "test/acc_raw"
    #: the names runs logged before metrics were named by role (results/ records carry them)
    LEGACY = {
        "test_acc": ACC,
        "test_acc_raw": ACC_RAW,
        "train_loss": "train/loss",
        "train_acc": "train/acc",
        "lr": "train/lr",
    }
    #: artifact: the resolved config (YAML)
    CONFIG = "config.yaml"
    #: artifact: one row per test mesh, these columns (accuracies in [0, 1], area-weighted)
    PER_MESH = "per_mesh.csv"
    PER_MESH_COLUMNS = ("mesh", "faces", "area", "acc_raw", "acc")
    #: the per-mesh columns a report may average
    MESH_METRICS = ("acc", "acc_raw")
    #: artifact: per-face arrays, keys `<prefix><mesh id>` with these dtypes
    PREDICTIONS = "predictions.npz"
    PREDICTION_ARRAYS = {"labels_": "int16", "labels_raw_": "int16", "probs_": "float16"}

    @staticmethod
    def tags(cfg, *, dataset, category: str, fold, features: str, split: str, config_hash: str, overrides=None) -> dict:
        """The run's tags: TAGS (what the report selects by), the seed and accelerator, and provenance: the
        fold's mesh ids and the Hydra overrides the run was launched with (so that `meshseg.results`
        can check a shipped record against the code), the machine, the package versions, and the SLURM job
        when one runs it (so a stuck run can be found and `scancel`led)."""
        return {
            "dataset": dataset.name,
            "category": category,
            "model": cfg.model.name,
            "branches": cfg.branches,
            "features": features,
            "split": split,
            "fold": fold.index,
            "refine": cfg.refine.name,
            "budget": cfg.budget.name,
            "config_hash": config_hash,
            "git_sha": git_sha(),
            "data_hash": dataset.data_hash,
            "seed": cfg.seed,
            "accelerator": cfg.trainer.accelerator,
            "fold_ids": json.dumps({"train": list(fold.train), "test": list(fold.test)}),
            **({"overrides": json.dumps(list(overrides))} if overrides is not None else {}),
            "machine": machine(cfg.trainer.accelerator),
            "versions": versions(),
            **({"slurm_job": _slurm_job()} if _slurm_job() else {}),
        }

    @staticmethod
    def name(category: str, fold: int, model: str, branches, features: str, split: str, budget: str) -> str:
        """The run's name, what differs between a sweep's runs first (the UI's table cuts names short):
        `Glasses f2 · cnn1d 3B f800 · 5fold · cpu`."""
        return f"{category} f{fold} · {model} {branches}B {features} · {split} · {budget}"

    @staticmethod
    def upgrade(metrics: dict) -> tuple[dict, dict]:
        """(metrics, count params) by today's names from a run's metrics under any earlier naming."""
        out, counts = {}, {}
        for k, v in metrics.items():
            if k.startswith("n_"):
                counts[k] = int(v)
            elif k.startswith("time_") and k.endswith("_s"):
                out[f"time/{k[5:]}"] = v
            elif k.endswith("_per_s") and "/" not in k:
                out[f"speed/{k}"] = v
            else:
                out[FoldRecord.LEGACY.get(k, k)] = v
        return out, counts

    @staticmethod
    def params(config: dict) -> dict[str, str]:
        """The run's params as the UI lists them: the resolved config flattened, a list as one value, the
        tracking settings left out (they say where a run is kept, not what it is)."""
        return {k: v for k, v in flatten(config, lists=False).items() if k.split(".")[0] != "tracking"}

    @staticmethod
    def predictions(meshes, probabilities, raw, labels) -> dict[str, np.ndarray]:
        """The per-face arrays of every test mesh, keyed `<prefix><mesh id>` (PREDICTION_ARRAYS)."""
        out = {}
        for m, p, r, lab in zip(meshes, probabilities, raw, labels):
            out.update({f"labels_{m.id}": lab, f"labels_raw_{m.id}": r, f"probs_{m.id}": p})
        return out


#: kept for callers of the earlier name
CONTRACT_TAGS = FoldRecord.TAGS


def flatten(node, prefix: str = "", lists: bool = True) -> dict[str, object]:
    """{"a.b.c": leaf} for nested dicts and lists (list items keyed by index; with lists=False a list is
    one leaf, written as JSON)."""
    if isinstance(node, list) and not lists:
        return {prefix: json.dumps(node, default=str)}
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else None
    if items is None:
        return {prefix: node}
    out: dict[str, object] = {}
    for k, v in items:
        out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k), lists))
    return out


def config_hash(config: dict, exclude=(), extra: dict | None = None, defaults: dict | None = None) -> str:
    """sha256 (16 hex) of the config's leaves except the `exclude` keys (a key excludes its subtree)
    and the `defaults` leaves that hold their default value, plus `extra` (e.g. the data hash)."""
    prefixes, defaults = tuple(exclude), defaults or {}
    leaves = {
        k: v
        for k, v in flatten(config).items()
        if not any(k == p or k.startswith(p + ".") for p in prefixes) and not (k in defaults and defaults[k] == v)
    }
    blob = json.dumps({"config": leaves, "extra": extra or {}}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def fold_identity(cfg, category: str, fold, data_hash: str) -> tuple[dict, str]:
    """The resolved config of one fold's run and its config hash: what `meshseg.run` logs and skips on,
    and what the report looks runs up by. `cfg` is the composed config or its resolved dict (the
    report resolves once per column and asks for every fold). `fold` is a `meshseg.data.splits.Fold`:
    its train and test mesh ids enter the hash, so another split file, or another way of dealing
    meshes into folds, never reuses a run of a different fold."""
    from omegaconf import DictConfig, OmegaConf

    config = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    config.update(category=category, fold=fold.index)
    extra = {"data_hash": data_hash, "train": list(fold.train), "test": list(fold.test)}
    tracking = config["tracking"]
    return config, config_hash(config, tracking["hash_exclude"], extra, tracking.get("hash_defaults"))


def system_tags(source: str, command: str, git: str) -> dict[str, str]:
    """MLflow's own run fields, which its UI shows: source, user, git commit, and the command line as the
    run's description (`mlflow.note.content`)."""
    import getpass

    try:
        user = getpass.getuser()
    except (KeyError, OSError):  # no name for this uid (some containers)
        user = "unknown"
    sha = git.removesuffix("+dirty")
    return {
        "mlflow.source.name": source,
        "mlflow.source.type": "JOB" if _slurm_job() else "LOCAL",
        "mlflow.user": user,
        **({"mlflow.source.git.commit": sha} if sha != "unknown" else {}),
        "mlflow.note.content": f"`{command}`",
    }


def _slurm_job() -> str | None:
    """The SLURM job running this process (array jobs as <array job>_<task>), or None outside SLURM."""
    import os

    env = os.environ
    if env.get("SLURM_ARRAY_JOB_ID") and env.get("SLURM_ARRAY_TASK_ID"):
        return f"{env['SLURM_ARRAY_JOB_ID']}_{env['SLURM_ARRAY_TASK_ID']}"
    return env.get("SLURM_JOB_ID")


def machine(accelerator: str = "cpu") -> str:
    """What ran it: the CPU model and its cores, and the GPU where one trained."""
    import os
    import platform

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    text = f"{cpu}, {os.cpu_count()} cores"
    if accelerator == "gpu":
        import torch

        if torch.cuda.is_available():
            text += f", {torch.cuda.get_device_name()}"
    return text


def versions() -> str:
    """The versions of Python and the packages that shape a result."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    out = [f"python {platform.python_version()}"]
    for name in ("meshseg", "torch", "numpy", "scipy", "scikit-learn", "pytorch-lightning", "mlflow"):
        try:
            out.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            pass
    return ", ".join(out)


def git_sha() -> str:
    """The package's git commit, '+dirty' when tracked files differ from it; 'unknown' outside git."""
    root = Path(__file__).resolve().parents[1]
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return sha + ("+dirty" if dirty else "")


#: where `make ui` serves a sqlite store's UI
UI_URL = "http://127.0.0.1:5000"

#: MLflow's store schemes (a `+driver` suffix is allowed on the database ones)
STORE_SCHEMES = ("sqlite", "postgresql", "mysql", "mssql", "file", "http", "https", "databricks")


def store_uri(uri: str) -> str:
    """A relative sqlite path made absolute (so workers and `mlflow ui` agree), its folder created.
    An unknown scheme is refused here, with what is allowed."""
    from urllib.parse import urlparse

    scheme = urlparse(uri).scheme.split("+")[0]
    if scheme not in ("", *STORE_SCHEMES) or (scheme == "" and "://" in uri):
        raise TrackingError(
            f"tracking.uri={uri}: unknown store scheme {scheme!r}; use sqlite:///PATH/mlflow.db, "
            f"http(s)://HOST:PORT (a tracking server) or one of {list(STORE_SCHEMES)}"
        )
    prefix = "sqlite:///"
    if uri.startswith(prefix):
        path = Path(uri[len(prefix) :]).expanduser().absolute()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise TrackingError(f"tracking.uri={uri}: cannot create the store's folder {path.parent} ({e})") from None
        if path.is_dir():
            raise TrackingError(f"tracking.uri={uri}: {path} is a folder; name the database file (…/mlflow.db)")
        return prefix + str(path)
    return uri


def check_store_exists(uri: str) -> None:
    """For commands that read a store (predict): a sqlite store that is not there is a mistyped path, not a
    new store to create empty."""
    prefix = "sqlite:///"
    if uri.startswith(prefix) and not Path(uri[len(prefix) :]).expanduser().is_file():
        raise TrackingError(f"tracking.uri={uri}: no such store (no file {Path(uri[len(prefix) :]).expanduser()})")


def check_server(uri: str, timeout: float = 5.0) -> None:
    """An http(s) store must answer its health check within `timeout` seconds: MLflow's own client
    retries for minutes before it gives up."""
    import urllib.error
    import urllib.request

    try:
        with urllib.request.urlopen(uri.rstrip("/") + "/health", timeout=timeout) as r:
            if r.status == 200:
                return
            problem = f"its health check answered HTTP {r.status}"
    except urllib.error.HTTPError as e:
        problem = f"its health check answered HTTP {e.code}"
    except (urllib.error.URLError, OSError) as e:
        problem = f"no MLflow server answers ({getattr(e, 'reason', e)})"
    raise TrackingError(f"tracking.uri={uri}: {problem}; start one with `mlflow server` or use a sqlite:/// store")


@contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    """An exclusive lock on `path` (created if missing) for the duration of the block: processes on
    one machine initialising one sqlite store take turns."""
    import fcntl

    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


#: the main thread's store call under way (its depth) and an interrupt that arrived during it
_IN_CALL = {"depth": 0, "pending": None}


def interrupt(reason: str) -> None:
    """Stop the fold, from a signal handler (meshseg.run.terminate_interrupts): KeyboardInterrupt(reason)
    now or, while a store call is under way on the main thread, the moment it returns. Raised inside the
    call, it can leave the call's sqlite write transaction open in this process, and the run's own end
    (KILLED) then waits on that lock until it fails ('database is locked')."""
    if _IN_CALL["depth"]:
        _IN_CALL["pending"] = reason
    else:
        raise KeyboardInterrupt(reason)


@contextmanager
def _whole_call():
    if threading.current_thread() is not threading.main_thread():  # signals interrupt the main thread only
        yield
        return
    _IN_CALL["depth"] += 1
    try:
        yield
    finally:
        _IN_CALL["depth"] -= 1
        if _IN_CALL["depth"] == 0 and _IN_CALL["pending"]:
            reason, _IN_CALL["pending"] = _IN_CALL["pending"], None
            raise KeyboardInterrupt(reason)


class _WholeCalls:
    """An MlflowClient whose every call runs to its end before an interrupt (`interrupt`) takes effect."""

    def __init__(self, client):
        self._client = client

    def __getattr__(self, name: str):
        attr = getattr(self._client, name)
        if not callable(attr):
            return attr

        def call(*args, **kwargs):
            with _whole_call():
                return attr(*args, **kwargs)

        return call


def _retry(fn, what: str, attempts: int = 8, transient: tuple[str, ...] = ("locked",)):
    """sqlite under several writer processes can report 'database is locked': back off and retry (any
    error whose text holds one of `transient`, case-blind). A tracking server that stays unreachable
    through MLflow's own HTTP retries is one TrackingError."""
    from mlflow.exceptions import MlflowException

    for i in range(attempts):
        try:
            return fn()
        except MlflowException as e:
            if gone := _server_gone(what, e):
                raise gone from None
            if not any(t in str(e).lower() for t in transient) or i == attempts - 1:
                raise
            log.warning("%s: store busy or a concurrent write won, retrying", what)
            time.sleep(0.2 * 2**i)


def _server_gone(what: str, e: Exception) -> TrackingError | None:
    """The one-line error for an MLflow HTTP call that failed for want of a server (MLflow's own retries
    spent), or None when `e` is something else."""
    text = str(e)
    if "failed with exception" not in text or "Max retries exceeded" not in text:
        return None
    reasons = ("Connection refused", "timed out", "Connection reset", "Name or service not known")
    why = next((r for r in reasons if r in text), "no connection")
    return TrackingError(f"{what}: the tracking server stopped answering ({why}); a rerun redoes this fold")


#: lease tags of a claimed run (Tracker.claim): who runs it, when it last said so, and the timing
LEASE_OWNER, LEASE_HEARTBEAT = "lease.owner", "lease.heartbeat"
LEASE_TIMEOUT, LEASE_INTERVAL = "lease.timeout_s", "lease.interval_s"


def _owner() -> str:
    import os
    import socket

    return f"{socket.gethostname()}:{os.getpid()}"


def _holds(run) -> bool:
    """Whether a run keeps its config from others: it is FINISHED, or RUNNING under a live lease."""
    return run.info.status == "FINISHED" or (run.info.status == "RUNNING" and _lease_alive(run))


def _lease_alive(run) -> bool:
    """Whether a RUNNING run's process is still at work: its heartbeat is recent and, when it runs on
    this host, its process exists (so a run killed outright here is taken over at once)."""
    import os
    import socket

    tags = run.data.tags
    try:
        age = time.time() - float(tags[LEASE_HEARTBEAT])
        timeout = float(tags.get(LEASE_TIMEOUT, 120))
    except (KeyError, ValueError):
        return False  # no lease: a run from before leases, or a damaged one
    host, _, pid = tags.get(LEASE_OWNER, "").rpartition(":")
    if host == socket.gethostname() and pid.isdigit():
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            pass  # it exists, under another user
    return age < timeout


class _Heartbeat:
    """A daemon thread that refreshes a run's heartbeat tag every lease interval until stopped."""

    def __init__(self, client, run_id: str):
        import threading

        self.client, self.run_id = client, run_id
        self.interval = float(client.get_run(run_id).data.tags.get(LEASE_INTERVAL, 30))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat-{run_id[:8]}", daemon=True)
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(self.interval):
            try:
                self.client.set_tag(self.run_id, LEASE_HEARTBEAT, f"{time.time():.0f}")
            except Exception as e:  # a store hiccup must not kill training; the next beat retries
                log.warning("heartbeat of run %s: %s", self.run_id, e)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)


class Tracker:
    """One MLflow experiment in one store."""

    def __init__(self, uri: str, experiment: str, artifact_dir: str | None = None):
        from mlflow import MlflowClient

        self.uri = store_uri(uri)
        if self.uri.startswith(("http://", "https://")):
            check_server(self.uri)
        if self.uri.startswith("sqlite:///"):
            # MLflow creates and migrates a new sqlite schema on first use; two processes doing that at
            # once collide ("duplicate column name"), so the first use happens under a lock beside the file.
            with _file_lock(Path(self.uri[len("sqlite:///") :] + ".lock")):
                self.client = _WholeCalls(MlflowClient(tracking_uri=self.uri))
                self.experiment_id = self._experiment(experiment, artifact_dir)
        else:
            self.client = _WholeCalls(MlflowClient(tracking_uri=self.uri))
            self.experiment_id = self._experiment(experiment, artifact_dir)

    def _experiment(self, name: str, artifact_dir: str | None) -> str:
        from mlflow.exceptions import MlflowException

        exp = _retry(lambda: self.client.get_experiment_by_name(name), "get experiment")
        if exp is not None:
            return exp.experiment_id
        location = None  # a server decides for itself
        if self.uri.startswith("sqlite:///"):  # a sqlite store keeps its artifacts beside its database file
            folder = Path(artifact_dir) if artifact_dir else Path(self.uri[len("sqlite:///") :]).parent / "artifacts"
            location = folder.expanduser().absolute().as_uri()
        try:
            return self.client.create_experiment(name, artifact_location=location)
        except MlflowException:  # another worker created it first
            return self.client.get_experiment_by_name(name).experiment_id

    def runs(self, filter_string: str = "") -> list:
        """All runs of the experiment matching an MLflow filter string."""
        out, token = [], None
        while True:
            page = self.client.search_runs([self.experiment_id], filter_string, max_results=1000, page_token=token)
            out.extend(page)
            token = page.token
            if not token:
                return out

    def finished(self, config_hash: str):
        """The FINISHED run with this config hash, or None."""
        runs = self.runs(f"tags.config_hash = '{config_hash}' and attributes.status = 'FINISHED'")
        return runs[0] if runs else None

    def claim(
        self,
        name: str,
        tags: dict,
        heartbeat_s: float = 30.0,
        lease_timeout_s: float = 120.0,
        attempts: int = 20,
        start_time: int | None = None,
    ) -> tuple[str | None, object | None]:
        """Create this config's run, RUNNING under a lease, unless the config is taken: returns (run id,
        None), or (None, the holder) when another run of the same `config_hash` is FINISHED or held by a
        live process.

        No lock is needed, so it works on any store: every claimant first creates its run, then looks
        at the others, and keeps the config only if it sees no other live run of it. Of two claimants
        the later to be stored sees the earlier, so two can never both keep it (start times cannot
        order them: a client stamps its start time before its run is stored). Claimants that saw each
        other all step back; if a moment later no live run is left, they try again after a random
        pause. A lease is live while its owner's heartbeat tag is younger than `lease_timeout_s` (and,
        on this host, while its process exists); a dead one is taken over and its run marked KILLED."""
        chash = tags["config_hash"]
        for attempt in range(attempts):
            lease = {
                LEASE_OWNER: _owner(),
                LEASE_HEARTBEAT: f"{time.time():.0f}",
                LEASE_TIMEOUT: f"{lease_timeout_s:g}",
                LEASE_INTERVAL: f"{heartbeat_s:g}",
            }
            mine = self._create(name, {**tags, **lease}, start_time).info.run_id
            try:
                others = [r for r in self._config_runs(chash) if r.info.run_id != mine]
                holders = [r for r in others if _holds(r)]
                if not holders:
                    for stale in others:
                        if stale.info.status == "RUNNING":  # its process died mid-run
                            self.client.set_tag(stale.info.run_id, "superseded_by", mine)
                            self.client.set_terminated(stale.info.run_id, "KILLED")
                    return mine, None
            except KeyboardInterrupt:  # Ctrl-C or SIGTERM (meshseg.run.terminate_interrupts) mid-claim
                self.client.set_terminated(mine, "KILLED")
                raise
            self.client.set_terminated(mine, "KILLED")  # a claim that stepped back is no run in progress
            self.client.delete_run(mine)
            time.sleep(random.uniform(0.05, 0.25) * min(attempt + 1, 4))
            # a holder that is still there is not a fellow claimant stepping back: it keeps the config
            holders = [r for r in self._config_runs(chash) if _holds(r)]
            if holders:
                return None, min(holders, key=lambda r: (r.info.status != "FINISHED", r.info.start_time))
        raise TrackingError(f"config {chash}: {attempts} claims in a row met other claimants; run it again")

    def _config_runs(self, chash: str) -> list:
        return self.runs(f"tags.config_hash = '{chash}'")

    def _create(self, name: str, tags: dict, start_time: int | None = None):
        from mlflow.utils.mlflow_tags import MLFLOW_RUN_NAME

        tags = {**{k: str(v) for k, v in tags.items()}, MLFLOW_RUN_NAME: name}
        return _retry(
            lambda: self.client.create_run(self.experiment_id, start_time=start_time, run_name=name, tags=tags),
            "create run",
        )

    @contextmanager
    def run(self, name: str, tags: dict, params: dict, run_id: str | None = None) -> Iterator[str]:
        """Yield a run's id (`run_id`, claimed before, or a new run) and end it FINISHED, FAILED (error
        text tagged) or KILLED. A claimed run's heartbeat is kept fresh meanwhile."""
        run_id = run_id or self._create(name, tags).info.run_id
        beat = None
        try:
            beat = _Heartbeat(self.client, run_id) if self._leased(run_id) else None
            self.log_params(run_id, params)
            yield run_id
        except KeyboardInterrupt:
            self._end(beat, run_id, "KILLED")
            raise
        except BaseException as e:
            text = "".join(traceback.format_exception_only(type(e), e)).strip()
            try:
                self.client.set_tag(run_id, "error", text[:5000])
                self.client.log_text(run_id, traceback.format_exc(), "error.txt")
                self._end(beat, run_id, "FAILED")
            except Exception as why:  # the store itself is gone: the run stays RUNNING until a rerun takes it over
                if beat is not None:
                    beat.stop()
                log.warning("run %s could not be marked FAILED: %s", run_id, str(why).splitlines()[0][:300])
            if gone := _server_gone(f"run {run_id}", e):  # e.g. an artifact upload: one line, not MLflow's page
                raise gone from None
            raise
        else:
            self._end(beat, run_id, "FINISHED")

    def _leased(self, run_id: str) -> bool:
        return LEASE_OWNER in self.client.get_run(run_id).data.tags

    def _end(self, beat, run_id: str, status: str) -> None:
        if beat is not None:
            beat.stop()
        _retry(lambda: self.client.set_terminated(run_id, status), "end run")

    def log_metrics(self, run_id: str, metrics: dict[str, float]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, 0) for k, v in metrics.items()]
        _retry(lambda: self.client.log_batch(run_id, metrics=items), "log metrics")

    def log_params(self, run_id: str, params: dict) -> None:
        from mlflow.entities import Param

        items = [Param(k, str(v)[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):
            _retry(lambda i=i: self.client.log_batch(run_id, params=items[i : i + 100]), "log params")

    def log_fold(
        self, run_id: str, config_yaml: str, rows: list[dict], predictions: dict[str, np.ndarray] | None
    ) -> None:
        """The fold's record as `FoldRecord` names it: the config, the per-mesh table (its columns in
        FoldRecord's order) and the per-face predictions, each array cast to its FoldRecord dtype (None: a
        run imported from `results/`, which carries no per-face arrays)."""
        R = FoldRecord
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            (d / R.CONFIG).write_text(config_yaml)
            buf = io.StringIO()
            writer = csv.DictWriter(buf, fieldnames=list(R.PER_MESH_COLUMNS))
            writer.writeheader()
            writer.writerows(rows)
            (d / R.PER_MESH).write_text(buf.getvalue())
            arrays = {}
            for key, a in (predictions or {}).items():
                prefix = max((p for p in R.PREDICTION_ARRAYS if key.startswith(p)), key=len, default=None)
                if prefix is None:
                    raise KeyError(f"prediction array {key!r} is not in the fold record: {list(R.PREDICTION_ARRAYS)}")
                arrays[key] = np.asarray(a).astype(R.PREDICTION_ARRAYS[prefix], copy=False)
            for name in (R.CONFIG, R.PER_MESH):
                self.client.log_artifact(run_id, str(d / name))
            if predictions is not None:
                np.savez_compressed(d / R.PREDICTIONS, **arrays)
                self.client.log_artifact(run_id, str(d / R.PREDICTIONS))

    def log_model(self, run_id: str, model) -> None:
        """The fold's model (`meshseg.predict.FoldModel`) as the run's `model/` artifact."""
        with tempfile.TemporaryDirectory() as tmp:
            model.save(Path(tmp))
            _retry(lambda: self.client.log_artifacts(run_id, tmp, "model"), "log model")

    def log_dataset(self, run_id: str, name: str, digest: str, source: str) -> None:
        """The run's data as MLflow's dataset input (the UI's Datasets column): `name` (dataset/category),
        `digest` (the data hash) and `source` (where the data is read from)."""
        from mlflow.entities import Dataset, DatasetInput, InputTag

        data = Dataset(name=name, digest=digest[:36], source_type="local", source=json.dumps({"uri": source}))
        inp = DatasetInput(data, [InputTag("mlflow.data.context", "training")])
        # MLflow's store looks a dataset up, then inserts it: two folds of one category that log it at
        # once race, and the loser gets a unique-key violation. Retried, it finds the winner's row.
        _retry(lambda: self.client.log_inputs(run_id, [inp]), "log dataset", transient=("locked", "unique"))

    def log_files(self, run_id: str, paths) -> None:
        """Files as top-level artifacts (the Hydra job's overrides and log); missing ones are skipped."""
        for p in paths:
            if Path(p).is_file():
                _retry(lambda p=p: self.client.log_artifact(run_id, str(p)), "log files")

    def _ui(self, ui: str | None) -> str:
        """The MLflow UI's address: the tracking server's own, or `ui` (`make ui`'s, for a sqlite store)."""
        base = self.uri if self.uri.startswith(("http://", "https://")) else (ui or UI_URL)
        return f"{base.rstrip('/')}/#/experiments/{self.experiment_id}/runs"

    def run_url(self, run_id: str, ui: str | None = None) -> str:
        """The run's page in the MLflow UI."""
        return f"{self._ui(ui)}/{run_id}"

    def runs_url(self, ui: str | None = None) -> str:
        """The experiment's runs table (MLflow 3 opens an experiment in its GenAI view otherwise)."""
        return f"{self._ui(ui)}?workflowType=machine_learning"

    def log_pictures(self, run_id: str, meshes, labels, rows: list[dict], n: int) -> None:
        """Artifacts the MLflow UI shows: renders/<mesh>.png (predicted beside ground truth) for up to
        `n` test meshes — the worst, the best, then the median by accuracy, so that what went wrong
        is in view — and confusion.png, the area-weighted confusion over every test mesh."""
        from meshseg.metrics import confusion_matrix
        from meshseg.render import confusion_png, label_comparison_png

        names = list(meshes[0].label_names)
        order = np.argsort([r["acc"] for r in rows], kind="stable")
        picks = list(dict.fromkeys([order[0], order[-1], order[len(order) // 2], *order]))[:n]
        confusion = sum(confusion_matrix(lab, m.labels, len(names), m.face_areas) for m, lab in zip(meshes, labels))
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            for i in picks:
                m = meshes[i]
                path = d / f"mesh_{m.id}.png"
                path.write_bytes(
                    label_comparison_png(
                        m.vertices, m.faces, labels[i], m.labels, names, title=f"{m.category} mesh {m.id}"
                    )
                )
                self.client.log_artifact(run_id, str(path), "renders")
            (d / "confusion.png").write_bytes(confusion_png(confusion, names, title="area-weighted, all test meshes"))
            self.client.log_artifact(run_id, str(d / "confusion.png"))

    def lightning_logger(self, run_id: str):
        """Lightning's MLflow logger writing epoch curves into this run (and leaving it open)."""
        from pytorch_lightning.loggers import MLFlowLogger

        class _FoldLogger(MLFlowLogger):
            def __init__(self, **kwargs):
                super().__init__(**kwargs)
                self._mlflow_client = _WholeCalls(self._mlflow_client)  # epoch curves are store writes too

            def finalize(self, status: str = "success") -> None:
                pass  # the run ends after evaluation, in Tracker.run

        return _FoldLogger(tracking_uri=self.uri, run_id=run_id)


def search_runs(uri: str, experiment: str, filter_string: str = "") -> list:
    """Every run of `experiment` in the store at `uri` that matches `filter_string`, all pages, each page
    call retried like every store call; [] when the experiment does not exist (it is never created)."""
    import os

    from mlflow import MlflowClient

    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # one bar per run otherwise
    client = MlflowClient(tracking_uri=store_uri(uri))
    exp = _retry(lambda: client.get_experiment_by_name(experiment), "reading the experiment")
    runs, token = [], None
    while exp is not None:
        page = _retry(
            lambda token=token: client.search_runs(
                [exp.experiment_id], filter_string, max_results=1000, page_token=token
            ),
            "searching runs",
        )
        runs.extend(page)
        token = page.token
        if not token:
            break
    return runs
