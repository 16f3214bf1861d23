"""A `-m` sweep's side of a run: which (category, fold) cells a sweep expands to (for meshseg's sweeper,
hydra_plugins/meshseg_sweeper), the sweep's parent run and its closing summary, a job's `job k/N` progress,
and what a job knows of the Hydra app it runs in (its overrides, its sweep and parent run, its log files)."""

from __future__ import annotations

import json
import logging
import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from meshseg.data.datasets import build_dataset
from meshseg.job import build_method, check_config, resolve_fold
from meshseg.timing import time_left

log = logging.getLogger("meshseg.run")

#: set by meshseg's sweeper for its jobs: how many there are and when the sweep began (time.time())
SWEEP_JOBS, SWEEP_START = "MESHSEG_SWEEP_JOBS", "MESHSEG_SWEEP_START"
#: set by meshseg's sweeper for its jobs: the sweep's parent run, which their fold runs are nested under
SWEEP_PARENT = "MESHSEG_SWEEP_PARENT"
#: MLflow's tag of a nested run: its parent run's id
PARENT_RUN_ID = "mlflow.parentRunId"
#: the jobs this process ran to the end (skipped ones not counted) and their seconds: the pace of `job k/N`
_PACE = {"jobs": 0, "seconds": 0.0}


def sweep_cells(cfg: DictConfig, category_given: bool, fold_given: bool) -> list[tuple[str | None, int | None]]:
    """The (category, fold) pairs a -m sweep adds to one combination of its overrides: every category
    unless the command line fixes it, every fold of each unless fixed (None where fixed). Fails at
    once on a bad value, before any job starts; also creates the tracking store, so that parallel
    workers never race to initialise it."""
    from meshseg.tracking import Tracker

    check_config(cfg)
    dataset = build_dataset(cfg.dataset)
    split = build_method(cfg).split
    categories = [dataset.check_category(cfg.category)] if category_given else dataset.categories
    cells: list[tuple[str | None, int | None]] = []
    for category in categories:
        if fold_given:
            resolve_fold(OmegaConf.merge(cfg, {"category": category}), dataset, split)
            cells.append((None if category_given else category, None))
        else:
            n = len(split.folds(dataset, category))
            cells.extend((None if category_given else category, f) for f in range(n))
    Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir)
    return cells


def job_progress() -> None:
    """`job k/N` of a -m sweep, with the time left at the pace of the jobs this process ran (none yet: no
    estimate; a resumed sweep's skipped jobs take seconds and would make it far too short)."""
    from hydra.core.hydra_config import HydraConfig

    n, start = os.environ.get(SWEEP_JOBS), os.environ.get(SWEEP_START)
    if not (n and start and HydraConfig.initialized() and HydraConfig.get().job.get("num") is not None):
        return
    k, n, elapsed = int(HydraConfig.get().job.num) + 1, int(n), time.time() - float(start)
    left = time_left(_PACE["seconds"], _PACE["jobs"], n - k + 1)
    log.info("job %d/%d (%.0f min into the sweep%s)", k, n, elapsed / 60, f", {left}" if left else "")


def job_done(seconds: float) -> None:
    """Count a job this process ran to the end (the pace of `job_progress`)."""
    _PACE["jobs"] += 1
    _PACE["seconds"] += seconds


def sweep_tag() -> dict[str, str]:
    """For a job of a `-m` sweep, {"sweep_id": the sweep's folder name} (its runs found together) and its parent run
    as MLflow's parent tag (its runs nested under the parent's row in the UI); {} for a single run."""
    from hydra.core.hydra_config import HydraConfig

    if not in_sweep():
        return {}
    parent = os.environ.get(SWEEP_PARENT)
    return {"sweep_id": Path(HydraConfig.get().sweep.dir).name, **({PARENT_RUN_ID: parent} if parent else {})}


@dataclass
class SweepSummary:
    """What a sweep did: jobs ran, skipped (their configs had FINISHED runs) and failed, and the test accuracy of
    each category's folds (a skipped fold's from its FINISHED run)."""

    ran: int
    skipped: int
    failed: int
    accuracies: dict[str, list[float]]
    seconds: float

    @classmethod
    def of(cls, outcomes: list, failed: int, seconds: float) -> SweepSummary:
        """From the return values of the jobs that completed (meshseg.run's FoldOutcome, as dicts)."""
        done = [d for d in outcomes if isinstance(d, dict) and "acc" in d]
        ran = sum(not d["skipped"] for d in done)
        accuracies: dict[str, list[float]] = {}
        for d in done:
            if not math.isnan(d["acc"]):  # a fold another live run holds has none yet
                accuracies.setdefault(d["category"], []).append(d["acc"])
        return cls(ran, len(done) - ran, failed, accuracies, seconds)

    def lines(self) -> str:
        """The sweep's closing lines."""
        s = self
        lines = [f"sweep: {s.ran} ran, {s.skipped} skipped, {s.failed} failed in {s.seconds / 60:.1f} min"]
        if s.accuracies:
            means = [f"{c} {100 * sum(a) / len(a):.2f} ({len(a)} folds)" for c, a in s.accuracies.items()]
            lines.append("sweep: mean test/acc by category (fold means, %): " + ", ".join(means))
        return "\n".join(lines)

    def metrics(self) -> dict[str, float]:
        """The parent run's metrics: the counts, the time, and test/acc/<category>, the mean of its folds'."""
        s = self
        counts = {"sweep/ran": s.ran, "sweep/skipped": s.skipped, "sweep/failed": s.failed, "time/sweep_s": s.seconds}
        return {**counts, **{f"test/acc/{c}": sum(a) / len(a) for c, a in s.accuracies.items()}}


def param_name(key: str) -> str:
    """An override's key as the name of a parent's param: without Hydra's +/~ prefix, and each character MLflow
    refuses in a param's name as ':' (a package override, `model@model.stage1=cnn1d`, is `model:model.stage1`)."""
    return re.sub(r"[^\w./ :-]", ":", key.lstrip("+~"))


@dataclass
class SweepParent:
    """A sweep's parent run (meshseg.tracking.sweeps), made or found by the process that expands the sweep; its id
    goes to the jobs through SWEEP_PARENT (launchers pass the environment on: joblib's workers, SLURM's jobs)."""

    tracker: object  # meshseg.tracking.Tracker
    run_id: str
    command: str
    closed: bool = False

    @classmethod
    def open(cls, trackings: list, overrides: list[str]) -> SweepParent | None:
        """The parent of the sweep of `overrides` (the command line's, the sweeper's params with them) in the store
        its jobs' `trackings` (their tracking configs) name; None when they name several (a swept tracking.uri)."""
        from meshseg.tracking import Tracker, git_sha, open_parent, sweep_key, system_tags

        stores = {(t.uri, t.experiment, t.artifact_dir) for t in trackings}
        if len(stores) != 1:
            log.warning("sweep: its jobs log to %d stores or experiments: no parent run", len(stores))
            return None
        t = trackings[0]
        tracker = Tracker(t.uri, t.experiment, t.artifact_dir)
        key, settings = sweep_key(overrides, t.hash_exclude)
        command = " ".join(["python -m meshseg.run -m", *overrides])
        tags = {**system_tags("meshseg.run", command, git_sha()), "sweep_overrides": json.dumps(settings)}
        params = {param_name(k): v for k, _, v in (o.partition("=") for o in settings)}
        name = f"sweep · {' '.join(settings) or 'every category and fold'}"
        run_id = open_parent(tracker, key, name[:250], tags, params)
        os.environ[SWEEP_PARENT] = run_id
        log.info("sweep %s: parent run %s", key, tracker.run_url(run_id))
        return cls(tracker, run_id, command)

    def close(self, summary: SweepSummary | None, status: str) -> None:
        """End the parent `status`, with the sweep's summary as its metrics and in its description (once: a sweep
        that ended with failed jobs exits through the sweeper's handler of interrupts)."""
        from meshseg.tracking import close_parent

        if self.closed:
            return
        self.closed = True
        lines = summary.lines().splitlines() if summary else []
        note = "\n\n".join([f"`{self.command}`", *lines])  # markdown: a paragraph each
        metrics = summary.metrics() if summary else {}
        close_parent(self.tracker, self.run_id, metrics, {"mlflow.note.content": note}, status)


def in_sweep() -> bool:
    """Whether this process runs a job of a -m sweep (the sweeper then lists its error with the others')."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def job_overrides() -> list[str] | None:
    """The overrides Hydra composed this job from (a sweep job's own included); None outside a Hydra app."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else None


def job_files() -> list[Path]:
    """The Hydra job's `overrides.yaml` and log file (none outside a Hydra app)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    hc = HydraConfig.get()
    out = Path(hc.runtime.output_dir)
    return [out / (hc.output_subdir or ".hydra") / "overrides.yaml", out / f"{hc.job.name}.log"]
