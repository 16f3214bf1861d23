"""`python -m meshseg.run`: train and evaluate one method on one fold of one category, logged as one
MLflow run (DESIGN "Tracking contract").

    python -m meshseg.run model=cnn1d branches=3 split=5fold -m           # every category x fold
    python -m meshseg.run dataset=psb category=Airplane fold=2 budget=cpu  # one run

Thin by design: compose, validate, wire data -> features -> training -> refine -> metrics ->
tracking. With -m, meshseg's sweeper (hydra_plugins/meshseg_sweeper) expands the categories and
folds that the command line does not fix.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import signal
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from meshseg import CONF_DIR
from meshseg.data.datasets import MeshDataset, build_dataset
from meshseg.data.splits import Fold, build_split, folds_for, split_name
from meshseg.errors import ConfigError, MeshsegError
from meshseg.features.sets import FeatureSet
from meshseg.refine import build_refinement
from meshseg.timing import Timings

log = logging.getLogger("meshseg.run")

BRANCHES = (1, 2, 3, 4)
RING_ADJACENCY = ("edge", "vertex")
RESAMPLE = ("fold", "epoch")  # budget.resample
#: the run tags a fold's saved model carries along (its model.yaml says where it came from)
ABOUT_MODEL = ("dataset", "category", "fold", "model", "branches", "features", "budget", "config_hash", "git_sha")


def known_settings() -> tuple[str, ...]:
    """The top-level keys a run config may have: conf/run.yaml's groups and its own keys."""
    import yaml

    primary = yaml.safe_load((Path(CONF_DIR) / "run.yaml").read_text())
    groups = [next(iter(d)) if isinstance(d, dict) else d for d in primary["defaults"]]
    keys = [*(g for g in groups if g != "_self_" and not g.startswith("override ")), *primary]
    return tuple(k for k in dict.fromkeys(keys) if k not in ("defaults", "hydra"))


def check_settings(keys) -> None:
    """Refuse a top-level key no config group or setting uses (`+modle=cnn1d` would otherwise train the
    default model with a junk key in its config hash), suggesting the nearest known one."""
    import difflib

    known = known_settings()
    for key in keys:
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise ConfigError(f"unknown setting {key!r}{hint}: meshseg.run takes {', '.join(known)}")


#: Hydra's flags whose next argument is their value, not an override
_VALUE_FLAGS = {
    *("-sc", "--shell-completion", "-cp", "--config-path", "-cn", "--config-name", "-cd", "--config-dir"),
    *("-c", "--cfg", "-p", "--package", "--experimental-rerun"),
}


def check_argv(argv: list[str]) -> None:
    """`check_settings` on the command line's overrides, before Hydra suggests `+key=` for a typo."""
    keys, flag_value = [], False
    for arg in argv:
        if flag_value or arg.startswith("-") or "=" not in arg:
            # -m, --flags, and the value of a flag that takes one (`-sc install=bash` is no setting)
            flag_value = arg in _VALUE_FLAGS
            continue
        key = arg.split("=", 1)[0].lstrip("+~").split(".")[0].split("/")[0].split("@")[0]
        if key != "hydra":
            keys.append(key)
    check_settings(keys)


def check_knobs(cfg: DictConfig) -> None:
    """Values no config group can check for itself; each message lists what is allowed."""
    check_settings([k for k in cfg.keys() if k != "hydra"])  # a sweep job's config carries hydra's own node
    if cfg.branches not in BRANCHES:
        raise ConfigError(f"branches={cfg.branches} is not allowed: choose one of {list(BRANCHES)}")
    fixed = cfg.model.get("branches")
    if fixed is not None and cfg.branches != fixed:
        raise ConfigError(
            f"branches={cfg.branches} is not allowed with model={cfg.model.name}: it takes branches={fixed}"
        )
    if cfg.ring_adjacency not in RING_ADJACENCY:
        raise ConfigError(f"ring_adjacency={cfg.ring_adjacency} is not allowed: choose one of {list(RING_ADJACENCY)}")
    b = cfg.budget
    if not (int(b.epochs) >= 1 and int(b.batch_size) >= 1 and (b.faces_per_mesh is None or int(b.faces_per_mesh) >= 1)):
        raise ConfigError(f"budget {b.name}: epochs and batch_size must be >= 1 and faces_per_mesh >= 1 or null")
    if b.get("resample", "fold") not in RESAMPLE:
        raise ConfigError(f"budget.resample={b.resample} is not allowed: choose one of {list(RESAMPLE)}")
    if not (isinstance(cfg.seed, int) and isinstance(cfg.workers, int) and cfg.workers >= 1):
        raise ConfigError(f"seed={cfg.seed} must be an integer and workers={cfg.workers} an integer >= 1")
    checkpoint_dir(cfg, "")  # tracking.checkpoints checked
    build_refinement(cfg.refine)  # its settings checked before any fold trains, not after
    check_fitter(cfg)
    build_split(cfg.split)
    FeatureSet.from_config(cfg.features)  # unknown groups and bad group parameters
    t = cfg.tracking
    if not (float(t.heartbeat_s) > 0 and float(t.lease_timeout_s) > 2 * float(t.heartbeat_s)):
        raise ConfigError(
            f"tracking.heartbeat_s={t.heartbeat_s} must be > 0 and tracking.lease_timeout_s="
            f"{t.lease_timeout_s} more than twice it"
        )


def check_fitter(cfg: DictConfig) -> None:
    """The model's fitter built with the run's training context: what the context refuses (a precision
    the CPU lacks) and what the fitter refuses with it (budget.resample=epoch for a forest) stops here,
    before any feature is computed or run created. Only settings away from the defaults can be refused, so
    the default path skips it (building a fitter imports torch and Lightning: seconds before the first line)."""
    if cfg.budget.get("resample", "fold") == "fold" and str(cfg.trainer.precision) in ("32-true", "32"):
        return
    from meshseg.training.context import TrainContext
    from meshseg.training.fitters import build_fitter

    build_fitter(cfg.model, TrainContext.from_config(cfg.budget, cfg.trainer, cfg.seed))


def resolve_cell(cfg: DictConfig, dataset: MeshDataset) -> tuple[str, Fold]:
    """The run's category (default: the dataset's first) and fold (default: 0), checked."""
    check_knobs(cfg)
    category = dataset.check_category(cfg.category) if cfg.category is not None else dataset.categories[0]
    folds = folds_for(dataset, category, cfg.split)
    index = 0 if cfg.fold is None else cfg.fold
    if not (isinstance(index, int) and 0 <= index < len(folds)):
        raise ConfigError(
            f"fold={cfg.fold} is out of range: "
            f"split {split_name(cfg.split)} of {category} has folds 0..{len(folds) - 1}"
        )
    return category, folds[index]


def sweep_cells(cfg: DictConfig, category_given: bool, fold_given: bool) -> list[tuple[str | None, int | None]]:
    """The (category, fold) pairs a -m sweep adds to one combination of its overrides: every category
    unless the command line fixes it, every fold of each unless fixed (None where fixed). Fails at
    once on a bad value, before any job starts; also creates the tracking store, so that parallel
    workers never race to initialise it."""
    from meshseg.tracking import Tracker

    dataset = build_dataset(cfg.dataset)
    check_knobs(cfg)
    categories = [dataset.check_category(cfg.category)] if category_given else dataset.categories
    cells: list[tuple[str | None, int | None]] = []
    for category in categories:
        if fold_given:
            resolve_cell(OmegaConf.merge(cfg, {"category": category}), dataset)
            cells.append((None if category_given else category, None))
        else:
            n = len(folds_for(dataset, category, cfg.split))
            cells.extend((None if category_given else category, f) for f in range(n))
    Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir)
    return cells


def _skipped(name: str, chash: str, holder) -> float:
    """Log why a fold is not run (its config is FINISHED, or a live process runs it); its accuracy or NaN."""
    from meshseg.tracking import FoldRecord

    acc = holder.data.metrics.get(FoldRecord.ACC, float("nan"))
    if holder.info.status == "FINISHED":
        log.info(
            "skip: %s — config %s already has FINISHED run %s (test/acc %.4f)", name, chash, holder.info.run_id, acc
        )
    else:
        log.info(
            "skip: %s — config %s is being run by run %s (%s)",
            name,
            chash,
            holder.info.run_id,
            holder.data.tags.get("lease.owner", "?"),
        )
    return acc


@dataclass
class Outcome:
    """What one fold's job did (a sweep's closing summary counts them): its test accuracy (area-weighted,
    refined; NaN for a fold another live run holds), and whether it was skipped."""

    category: str
    fold: int
    acc: float
    skipped: bool


def run(cfg: DictConfig) -> float:
    """One fold (see `run_fold`); returns its test accuracy."""
    return run_fold(cfg).acc


def run_fold(cfg: DictConfig) -> Outcome:
    """One fold: skip if its config already has a FINISHED run (or a live one), else resolve -> fit and
    predict -> refine -> score -> record."""
    from meshseg.tracking import FoldRecord, Lease, RunKey, Tracker, fold_identity, system_tags

    # resolve: every setting checked, the fold's identity, and whether it has run already
    t0 = time.perf_counter()
    sweep_progress()
    setup_trainer(cfg.trainer)
    dataset = build_dataset(cfg.dataset)
    category, fold = resolve_cell(cfg, dataset)
    features, refinement = FeatureSet.from_config(cfg.features), build_refinement(cfg.refine)
    config, chash = fold_identity(cfg, category, fold, dataset.data_hash)
    split = split_name(cfg.split)
    key = RunKey(
        dataset=dataset.name,
        category=category,
        model=cfg.model.name,
        branches=cfg.branches,
        features=features.name,
        split=split,
        fold=fold.index,
        refine=cfg.refine.name,
        budget=cfg.budget.name,
        config_hash=chash,
        data_hash=dataset.data_hash,
    )
    name = key.name
    tracker = Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir)
    done = tracker.finished(chash) if cfg.tracking.skip_finished else None
    if done is not None:
        return Outcome(category, fold.index, _skipped(name, chash, done), True)
    tags = FoldRecord.tags(key, fold, seed=cfg.seed, accelerator=cfg.trainer.accelerator, overrides=job_overrides())
    command = " ".join(["python -m meshseg.run", *(job_overrides() or [])])
    tags.update(system_tags("meshseg.run", command, tags["git_sha"]), **sweep_tag())
    with terminate_interrupts():  # from the claim on: SIGTERM ends the run KILLED wherever it lands
        run_id = None
        if cfg.tracking.skip_finished:  # claim the config: a concurrent sweep may have taken it since the check
            run_id, holder = tracker.claim(name, tags, Lease(cfg.tracking.heartbeat_s, cfg.tracking.lease_timeout_s))
            if run_id is None:
                return Outcome(category, fold.index, _skipped(name, chash, holder), True)
        outcome = _recorded(cfg, config, tags, tracker, name, run_id, dataset, fold, features, refinement)
    _PACE["jobs"] += 1
    _PACE["seconds"] += time.perf_counter() - t0
    return outcome


def _recorded(cfg, config, tags, tracker, name: str, run_id, dataset, fold: Fold, features, refinement) -> Outcome:
    """The fold's run (`run_id`: claimed, or None for a new one) from start to FINISHED, FAILED or KILLED."""
    from meshseg.tracking import FoldRecord

    category, chash = tags["category"], tags["config_hash"]
    with tracker.run(name, tags, FoldRecord.params(config), run_id) as run_id:
        log.info("run: %s (config %s, %d train / %d test meshes)", name, chash, len(fold.train), len(fold.test))
        log.info("run %s: %s", run_id, tracker.run_url(run_id))
        tracker.log_dataset(run_id, f"{dataset.name}/{category}", dataset.data_hash, dataset_source(dataset))
        try:
            with system_metrics(cfg.tracking, tracker, run_id):
                metrics = _fold(cfg, config, tags, tracker, run_id, dataset, fold, features, refinement)
        finally:  # the job's overrides and log, also (especially) for a run that failed
            try:
                tracker.log_files(run_id, job_files())
            except Exception as e:  # never hides what ended the run
                log.warning("run %s: its log and overrides were not stored: %s", run_id, str(e)[:300])
    log.info(
        "done: %s test/acc %.4f (raw %.4f), train %.1f s, run %s",
        name,
        metrics[FoldRecord.ACC],
        metrics[FoldRecord.ACC_RAW],
        metrics["time/train_s"],
        run_id,
    )
    return Outcome(category, fold.index, float(metrics[FoldRecord.ACC]), False)


def _fold(cfg, config: dict, tags: dict, tracker, run_id: str, dataset, fold: Fold, features, refinement) -> dict:
    """Fit and predict, refine, score, record: the body of one fold's run (`config` and `tags`: its resolved
    config and its tags). Returns its metrics."""
    from meshseg.metrics import mesh_scores
    from meshseg.predict import FoldModel
    from meshseg.tracking import FoldRecord
    from meshseg.training.context import TrainContext
    from meshseg.training.data import FeatureSource
    from meshseg.training.fit import fit_predict

    # fit and predict
    category = tags["category"]
    source = FeatureSource(dataset, category, features, cfg.paths.cache_dir, cfg.branches, cfg.ring_adjacency)
    checkpoints = checkpoint_dir(cfg, tags["config_hash"])
    logger = tracker.lightning_logger(run_id)
    ctx = TrainContext.from_config(cfg.budget, cfg.trainer, cfg.seed, logger, checkpoints and str(checkpoints))
    preds = fit_predict(source, fold, cfg.model, cfg.budget.faces_per_mesh, ctx, cfg.workers)
    timings = Timings(preds.timings)
    # refine: the refinement's own per-mesh inputs (e.g. AGD) come from the feature cache
    log.info("refining %d test meshes (%s)", len(preds.meshes), cfg.refine.name)
    with timings("refine"):
        raw = [p.argmax(axis=1) for p in preds.probabilities]
        labels = [
            refinement(m, p, source.groups(m, refinement.needs)) for m, p in zip(preds.meshes, preds.probabilities)
        ]
    # score
    rows = mesh_scores(preds.meshes, raw, labels)
    metrics = {
        FoldRecord.ACC: np.mean([r["acc"] for r in rows]),
        FoldRecord.ACC_RAW: np.mean([r["acc_raw"] for r in rows]),
        "speed/train_samples_per_s": preds.counts["train_samples"] * preds.counts["epochs"] / preds.timings["train"],
        "speed/predict_faces_per_s": preds.counts["test_faces"] / max(preds.timings.get("predict", 0.0), 1e-9),
    }
    # record (the timings last, so that they include the recording itself)
    log.info("logging predictions%s", ", the model" if cfg.tracking.log_model else "")
    with timings("log"):
        tracker.log_params(run_id, {f"n_{k}": v for k, v in preds.counts.items()})
        arrays = FoldRecord.predictions(preds.meshes, preds.probabilities, raw, labels)
        tracker.log_fold(run_id, OmegaConf.to_yaml(config), rows, arrays)
        if cfg.tracking.log_model:
            about = {"run_id": run_id, **{k: tags[k] for k in ABOUT_MODEL}}
            tracker.log_model(run_id, FoldModel.of_fold(config, preds, dataset.label_names(category), about))
    if cfg.tracking.renders:
        log.info("rendering %d test meshes", min(int(cfg.tracking.renders), len(preds.meshes)))
        with timings("pictures"):
            tracker.log_pictures(run_id, preds.meshes, labels, rows, int(cfg.tracking.renders))
    metrics.update({f"time/{k}_s": v for k, v in timings.items()})
    tracker.log_metrics(run_id, metrics)
    if checkpoints is not None:  # the fold is recorded: nothing left to resume
        shutil.rmtree(checkpoints, ignore_errors=True)
    return metrics


def checkpoint_dir(cfg: DictConfig, chash: str) -> Path | None:
    """Where a fold keeps its per-epoch checkpoints (`tracking.checkpoints`: auto = at budget=paper, where a
    fold trains for hours), keyed by its config hash so that the rerun of a killed fold finds them."""
    on = cfg.tracking.get("checkpoints", "auto")
    if on not in (True, False, "auto"):
        raise ConfigError(f"tracking.checkpoints={on} is not allowed: choose auto, true or false")
    if on is False or (on == "auto" and cfg.budget.name != "paper"):
        return None
    return Path(cfg.paths.cache_dir) / "checkpoints" / chash


@contextmanager
def terminate_interrupts():
    """While a fold runs, SIGTERM (`scancel`, `kill`, a job's time limit) and Ctrl-C interrupt it, so its run
    ends KILLED instead of staying RUNNING: submitit's jobs ignore SIGTERM, and SLURM follows it with
    SIGKILL. An interrupt waits for the store call under way, if any (meshseg.tracking.interrupt). Signals
    reach the main thread only; elsewhere this does nothing."""
    from meshseg.tracking import interrupt

    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        interrupt(f"{signal.Signals(signum).name} received")

    previous = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def dataset_source(dataset: MeshDataset) -> str:
    """Where a dataset's meshes are read from: its root folder, or the generator for synthetic data."""
    root = getattr(dataset, "root", None)
    return str(Path(root).absolute()) if root is not None else f"meshseg.data.synthetic ({dataset.name})"


@contextmanager
def system_metrics(tracking: DictConfig, tracker, run_id: str):
    """MLflow's CPU, memory and GPU samples as the run's system metrics, when `tracking.system_metrics`."""
    if not tracking.get("system_metrics"):
        yield
        return
    import mlflow
    from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

    mlflow.set_tracking_uri(tracker.uri)  # the monitor logs through the default client
    monitor = SystemMetricsMonitor(run_id, sampling_interval=10, samples_before_logging=1)
    monitor.start()
    try:
        yield
    finally:
        monitor.finish()


def job_files() -> list[Path]:
    """The Hydra job's `overrides.yaml` and log file (none outside a Hydra app)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    hc = HydraConfig.get()
    out = Path(hc.runtime.output_dir)
    return [out / (hc.output_subdir or ".hydra") / "overrides.yaml", out / f"{hc.job.name}.log"]


#: set by meshseg's sweeper for its jobs: how many there are and when the sweep began (time.time())
SWEEP_JOBS, SWEEP_START = "MESHSEG_SWEEP_JOBS", "MESHSEG_SWEEP_START"
#: the jobs this process ran to the end (skipped ones not counted) and their seconds: the pace of `job k/N`
_PACE = {"jobs": 0, "seconds": 0.0}


def sweep_progress() -> None:
    """`job k/N` of a -m sweep, with the time left at the pace of the jobs this process ran (none yet: no
    estimate; a resumed sweep's skipped jobs take seconds and would make it far too short)."""
    import os

    from hydra.core.hydra_config import HydraConfig

    n, start = os.environ.get(SWEEP_JOBS), os.environ.get(SWEEP_START)
    if not (n and start and HydraConfig.initialized() and HydraConfig.get().job.get("num") is not None):
        return
    k, n, elapsed = int(HydraConfig.get().job.num) + 1, int(n), time.time() - float(start)
    pace = _PACE["seconds"] / _PACE["jobs"] if _PACE["jobs"] else 0.0
    left = f", about {pace * (n - k + 1) / 60:.0f} min left" if pace else ""
    log.info("job %d/%d (%.0f min into the sweep%s)", k, n, elapsed / 60, left)


def sweep_tag() -> dict[str, str]:
    """{"sweep_id": the sweep's folder name} for a job of a `-m` sweep, so its runs can be found together."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return {}
    return {"sweep_id": Path(HydraConfig.get().sweep.dir).name}


def job_overrides() -> list[str] | None:
    """The overrides Hydra composed this job from (a sweep job's own included); None outside a Hydra app."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else None


def setup_trainer(trainer: DictConfig) -> None:
    """Process-wide settings of the trainer config: torch's thread count, glibc's malloc tuning."""
    import torch

    from meshseg.training.malloc import tune_glibc_malloc

    if trainer.threads:
        torch.set_num_threads(int(trainer.threads))
    if trainer.get("malloc_tune"):
        tune_glibc_malloc()  # speed only: results are the same either way


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="run")
def _app(cfg: DictConfig) -> dict | None:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    logging.getLogger("pytorch_lightning.utilities.rank_zero").setLevel(logging.WARNING)  # no device banners
    try:
        return dataclasses.asdict(run_fold(cfg))
    except MeshsegError as e:
        if HydraConfig.get().mode == RunMode.MULTIRUN:
            raise  # the sweeper lists it with the other jobs' outcomes, then exits non-zero
        sys.exit(f"error: {e}")


def main() -> None:
    """`python -m meshseg.run`: the command line's settings checked, then the Hydra app."""
    try:
        check_argv(sys.argv[1:])
    except MeshsegError as e:
        sys.exit(f"error: {e}")
    _app()


if __name__ == "__main__":
    main()
