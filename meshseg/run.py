"""`python -m meshseg.run`: train and evaluate one method on one fold of one category, logged as one
MLflow run (DESIGN "Tracking contract").

    python -m meshseg.run model=cnn1d branches=3 split=5fold -m           # every category x fold
    python -m meshseg.run dataset=psb category=Airplane fold=2 budget=cpu  # one run

Thin by design: `run` is the fold's recipe, resolve -> features -> fit -> predict -> refine -> score ->
record. The fold job is resolved and checked in meshseg/job.py; with -m, meshseg's sweeper
(hydra_plugins/meshseg_sweeper, meshseg/sweep.py) expands the categories and folds the command line does
not fix.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from meshseg import CONF_DIR
from meshseg.cli import check_argv, command, user_errors
from meshseg.job import FoldJob
from meshseg.signals import terminate_interrupts
from meshseg.sweep import in_sweep, job_done, job_files, job_overrides, job_progress, sweep_tag
from meshseg.timing import Timings

log = logging.getLogger("meshseg.run")

#: the run tags a fold's saved model carries along (its model.yaml says where it came from)
ABOUT_MODEL = ("dataset", "category", "fold", "model", "branches", "features", "budget", "config_hash", "git_sha")


@dataclass
class FoldOutcome:
    """What one fold's job did (a sweep's closing summary counts them): its test accuracy (area-weighted,
    refined; NaN for a fold another live run holds), and whether it was skipped."""

    category: str
    fold: int
    acc: float
    skipped: bool


def run(cfg: DictConfig) -> FoldOutcome:
    """One fold: resolve it (every setting checked, its identity); skip it if its config already has a
    FINISHED run (or a live one); else claim it and record it from start to FINISHED, FAILED or KILLED."""
    from meshseg.tracking import Lease, Tracker, system_tags

    start = time.perf_counter()
    job_progress()
    setup_process(cfg.trainer)
    overrides = job_overrides()
    job = FoldJob.from_config(cfg, overrides)
    t = job.tracking
    tracker = Tracker(t["uri"], t["experiment"], t["artifact_dir"])
    holder = tracker.finished(job.key.config_hash) if t["skip_finished"] else None
    if holder is not None:
        return skipped(job, holder)
    command_line = " ".join(["python -m meshseg.run", *(overrides or [])])
    tags = {**job.tags, **system_tags("meshseg.run", command_line, job.tags["git_sha"]), **sweep_tag()}
    with terminate_interrupts():  # from the claim on: SIGTERM ends the run KILLED wherever it lands
        run_id = None
        if t["skip_finished"]:  # claim the config: a concurrent sweep may have taken it since the check
            run_id, holder = tracker.claim(job.key.name, tags, Lease(t["heartbeat_s"], t["lease_timeout_s"]))
            if run_id is None:
                return skipped(job, holder)
        acc = recorded(job, tags, tracker, run_id)
    job_done(time.perf_counter() - start)
    return FoldOutcome(job.key.category, job.fold.index, acc, False)


def recorded(job: FoldJob, tags: dict, tracker, run_id: str | None) -> float:
    """The fold's run (`run_id`: claimed, or None for a new one) around `fold`; its test accuracy."""
    from meshseg.tracking import FoldRecord

    with tracker.run(job.key.name, tags, FoldRecord.params(job.config), run_id) as run_id:
        fold = job.fold
        log.info(
            "run: %s (config %s, %d train / %d test meshes)",
            job.key.name,
            job.key.config_hash,
            len(fold.train),
            len(fold.test),
        )
        log.info("run %s: %s", run_id, tracker.run_url(run_id))
        tracker.log_dataset(run_id, f"{job.dataset.name}/{job.key.category}", job.dataset.data_hash, job.dataset.source)
        try:
            with system_metrics(tracker, run_id, job.tracking.get("system_metrics")):
                metrics = fold_recipe(job, tracker, run_id)
        finally:  # the job's overrides and log, also (especially) for a run that failed
            try:
                tracker.log_files(run_id, job_files())
            except Exception as e:  # never hides what ended the run
                log.warning("run %s: its log and overrides were not stored: %s", run_id, str(e)[:300])
    acc = metrics[FoldRecord.ACC]
    log.info(
        "done: %s test/acc %.4f (raw %.4f), train %.1f s, run %s",
        job.key.name,
        acc,
        metrics[FoldRecord.ACC_RAW],
        metrics["time/train_s"],
        run_id,
    )
    return float(acc)


def fold_recipe(job: FoldJob, tracker, run_id: str) -> dict:
    """Features -> fit -> predict -> refine -> score -> record: the body of one fold's run. Its metrics."""
    from meshseg.metrics import mesh_scores
    from meshseg.predict import FoldModel
    from meshseg.tracking import FoldRecord
    from meshseg.training.data import FeatureSource
    from meshseg.training.fit import fit_predict

    # features, fit, predict: the fit logs to the run and checkpoints under the fold's config hash
    source = FeatureSource(job.dataset, job.key.category, job.features, job.cache_dir, job.branches, job.ring_adjacency)
    fitter = job.fitter
    fitter.context = dataclasses.replace(
        fitter.context, logger=tracker.lightning_logger(run_id), checkpoint_dir=job.checkpoints and str(job.checkpoints)
    )
    preds = fit_predict(source, job.fold, fitter, job.faces_per_mesh, job.workers)
    timings = Timings(preds.timings)
    # refine: the refinement's own per-mesh inputs (e.g. AGD) come from the feature cache
    log.info("refining %d test meshes (%s)", len(preds.meshes), job.tags["refine"])
    with timings("refine"):
        raw = [p.argmax(axis=1) for p in preds.probabilities]
        refine = job.refinement
        labels = [refine(m, p, source.groups(m, refine.needs)) for m, p in zip(preds.meshes, preds.probabilities)]
    # score
    rows = mesh_scores(preds.meshes, raw, labels)
    metrics = {
        FoldRecord.ACC: np.mean([r["acc"] for r in rows]),
        FoldRecord.ACC_RAW: np.mean([r["acc_raw"] for r in rows]),
        "speed/train_samples_per_s": preds.counts["train_samples"] * preds.counts["epochs"] / preds.timings["train"],
        "speed/predict_faces_per_s": preds.counts["test_faces"] / max(preds.timings.get("predict", 0.0), 1e-9),
    }
    # record (the timings last, so that they include the recording itself)
    log_model, renders = job.tracking["log_model"], int(job.tracking["renders"] or 0)
    log.info("logging predictions%s", ", the model" if log_model else "")
    with timings("log"):
        tracker.log_params(run_id, {f"n_{k}": v for k, v in preds.counts.items()})
        arrays = FoldRecord.predictions(preds.meshes, preds.probabilities, raw, labels)
        tracker.log_fold(run_id, OmegaConf.to_yaml(job.config), rows, arrays)
        if log_model:
            about = {"run_id": run_id, **{k: job.tags[k] for k in ABOUT_MODEL}}
            label_names = job.dataset.label_names(job.key.category)
            tracker.log_model(run_id, FoldModel.of_fold(job.config, preds, label_names, about))
    if renders:
        log.info("rendering %d test meshes", min(renders, len(preds.meshes)))
        with timings("pictures"):
            tracker.log_pictures(run_id, preds.meshes, labels, rows, renders)
    metrics.update({f"time/{k}_s": v for k, v in timings.items()})
    tracker.log_metrics(run_id, metrics)
    if job.checkpoints is not None:  # the fold is recorded: nothing left to resume
        shutil.rmtree(job.checkpoints, ignore_errors=True)
    return metrics


def skipped(job: FoldJob, holder) -> FoldOutcome:
    """Log why a fold is not run (its config is FINISHED, or a live process runs it); its accuracy or NaN."""
    from meshseg.tracking import FoldRecord

    acc = holder.data.metrics.get(FoldRecord.ACC, float("nan"))
    if holder.info.status == "FINISHED":
        log.info(
            "skip: %s — config %s already has FINISHED run %s (test/acc %.4f)",
            job.key.name,
            job.key.config_hash,
            holder.info.run_id,
            acc,
        )
    else:
        owner = holder.data.tags.get("lease.owner", "?")
        log.info(
            "skip: %s — config %s is being run by run %s (%s)",
            job.key.name,
            job.key.config_hash,
            holder.info.run_id,
            owner,
        )
    return FoldOutcome(job.key.category, job.fold.index, acc, True)


@contextmanager
def system_metrics(tracker, run_id: str, on: bool):
    """MLflow's CPU, memory and GPU samples as the run's system metrics, when `tracking.system_metrics`."""
    if not on:
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


def setup_process(trainer: DictConfig) -> None:
    """Process-wide settings of the trainer config: torch's thread count, glibc's malloc tuning."""
    import torch

    from meshseg.training.malloc import tune_glibc_malloc

    if trainer.threads:
        torch.set_num_threads(int(trainer.threads))
    if trainer.get("malloc_tune"):
        tune_glibc_malloc()  # speed only: results are the same either way


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="run")
def _app(cfg: DictConfig) -> dict | None:
    logging.getLogger("pytorch_lightning.utilities.rank_zero").setLevel(logging.WARNING)  # no device banners
    if in_sweep():  # the sweeper lists a job's error with the other jobs' outcomes, then exits non-zero
        return dataclasses.asdict(run(cfg))
    with user_errors():
        return dataclasses.asdict(run(cfg))


@command
def main() -> None:
    """`python -m meshseg.run`: the command line's settings checked, then the Hydra app."""
    check_argv(sys.argv[1:])
    _app()


if __name__ == "__main__":
    main()
