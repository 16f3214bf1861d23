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

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from meshseg import CONF_DIR
from meshseg.cli import command, user_errors
from meshseg.job import FoldJob, FoldOutcome, check_argv
from meshseg.memory import peak_mib, reset_peak
from meshseg.signals import terminate_interrupts
from meshseg.sweep import in_sweep, job_done, job_files, job_overrides, job_progress, sweep_tag
from meshseg.timing import Timings

log = logging.getLogger("meshseg.run")


def run(cfg: DictConfig) -> FoldOutcome:
    """One fold: resolve -> features -> fit -> predict -> refine -> score -> record, as one MLflow run. A fold
    whose config already has a FINISHED run (or a live one) is skipped; its run ends FINISHED, FAILED or KILLED."""
    from meshseg.metrics import area_accuracy, mesh_scores
    from meshseg.pyfunc import log_fold_model
    from meshseg.tracking import FoldRecord, Lease, Tracker, system_tags
    from meshseg.training.data import FeatureSource
    from meshseg.training.fit import fit_predict

    start = time.perf_counter()
    job_progress()
    setup_process(cfg.trainer)
    # resolve: every setting checked, the method's parts built, the fold's identity; nothing computed yet
    overrides = job_overrides()
    job = FoldJob.from_config(cfg, overrides)
    key, t = job.key, job.tracking
    tracker = Tracker(t["uri"], t["experiment"], t["artifact_dir"])
    holder = tracker.finished(key.config_hash) if t["skip_finished"] else None
    if holder is not None:
        return job.skipped(holder)
    command_line = " ".join(["python -m meshseg.run", *(overrides or [])])
    tags = {**job.tags, **system_tags("meshseg.run", command_line, job.tags["git_sha"]), **sweep_tag()}
    params = FoldRecord.params(job.config)
    peak_is_this_runs = reset_peak()  # a sweep's jobs share the process: the peak from here on is this run's
    # from the claim on: SIGTERM ends the run KILLED wherever it lands, so nothing may run between the claim
    # and tracker.run, which ends it (a signal there left the claimed run RUNNING)
    with terminate_interrupts():
        run_id = None
        if t["skip_finished"]:  # claim the config: a concurrent sweep may have taken it since the check
            run_id, holder = tracker.claim(key.name, tags, Lease(t["heartbeat_s"], t["lease_timeout_s"]))
            if run_id is None:
                return job.skipped(holder)
        with (
            tracker.run(key.name, tags, params, run_id) as run_id,
            tracker.system_metrics(run_id, t["system_metrics"]),
            tracker.files_at_end(run_id, job_files),
        ):
            fold = job.fold
            log.info(
                "run: %s (config %s, %d train / %d test meshes)",
                key.name,
                key.config_hash,
                len(fold.train),
                len(fold.test),
            )
            log.info("run %s: %s", run_id, tracker.run_url(run_id))
            tracker.log_dataset(run_id, f"{key.dataset}/{key.category}", key.data_hash, job.dataset.source)
            # features, fit, predict: the fit logs to the run and checkpoints under the fold's config hash
            source = FeatureSource(
                job.dataset, key.category, job.features, job.cache_dir, key.branches, job.ring_adjacency, fold
            )
            fitter = job.fitter
            fitter.context = dataclasses.replace(
                fitter.context,
                logger=tracker.lightning_logger(run_id),
                checkpoint_dir=job.checkpoints and str(job.checkpoints),
            )
            preds = fit_predict(source, fitter, job.faces_per_mesh, job.workers)
            timings = Timings(preds.timings)
            # refine: its settings as configured, or chosen on held-out training meshes (refine.search); its
            # per-mesh inputs (e.g. AGD) come from the feature cache
            fitted = job.refinement.fitted(preds, source, area_accuracy, timings)
            refine = fitted.refinement
            log.info("refining %d test meshes (%s)", len(preds.meshes), key.refine)
            with timings("refine"):
                raw = [p.argmax(axis=1) for p in preds.probabilities]
                labels = [
                    refine(m, p, source.groups(m, refine.needs)) for m, p in zip(preds.meshes, preds.probabilities)
                ]
            # score
            rows = mesh_scores(preds.meshes, raw, labels)
            metrics = {
                FoldRecord.ACC: np.mean([r["acc"] for r in rows]),
                FoldRecord.ACC_RAW: np.mean([r["acc_raw"] for r in rows]),
                "speed/train_samples_per_s": preds.counts["train_samples"]
                * preds.counts["epochs"]
                / preds.timings["train"],
                "speed/predict_faces_per_s": preds.counts["test_faces"] / max(preds.timings.get("predict", 0.0), 1e-9),
                **fitted.metrics,
                **fitter.fitted(),
            }
            # record (the timings last, so that they include the recording itself)
            log.info("logging predictions%s", ", the model" if t["log_model"] else "")
            model_id = None
            with timings("log"):
                tracker.log_params(run_id, {f"n_{k}": v for k, v in preds.counts.items()})
                arrays = FoldRecord.predictions(preds.meshes, preds.probabilities, raw, labels)
                tracker.log_fold(run_id, OmegaConf.to_yaml(job.config), rows, arrays)
                for name, data in fitted.records.items():
                    tracker.log_json(run_id, name, data)
                if t["log_model"]:  # an MLflow logged model (meshseg.pyfunc), which meshseg.predict reads too
                    model_id = log_fold_model(tracker, run_id, job, preds, fitted.settings)
            if renders := int(t["renders"] or 0):
                log.info("rendering %d test meshes", min(renders, len(preds.meshes)))
                with timings("pictures"):
                    tracker.log_pictures(run_id, preds.meshes, labels, rows, renders)
            metrics.update({f"time/{k}_s": v for k, v in timings.items()})
            if peak_is_this_runs and (peak := peak_mib()) is not None:
                metrics["memory/peak_rss_mib"] = peak
            tracker.log_metrics(run_id, metrics, model_id)  # the model's metrics too (the UI's Models tab)
    if job.checkpoints is not None:  # the fold is recorded: nothing left to resume
        shutil.rmtree(job.checkpoints, ignore_errors=True)
    acc = float(metrics[FoldRecord.ACC])
    log.info(
        "done: %s test/acc %.4f (raw %.4f), train %.1f s, run %s",
        key.name,
        acc,
        metrics[FoldRecord.ACC_RAW],
        metrics["time/train_s"],
        run_id,
    )
    job_done(time.perf_counter() - start)
    return FoldOutcome(key.category, key.fold, acc, False)


def setup_process(trainer: DictConfig) -> None:
    """Process-wide settings of the trainer config: the thread count of torch and of numpy's BLAS and OpenMP
    pools, glibc's malloc tuning."""
    import torch
    from threadpoolctl import threadpool_limits

    from meshseg.training.malloc import tune_glibc_malloc

    if trainer.threads:
        torch.set_num_threads(int(trainer.threads))
        # BLAS too: beside two workers a 2-thread BLAS made PCA & NN's principal axes 13.6x slower (benchmarks/)
        threadpool_limits(limits=int(trainer.threads))
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
