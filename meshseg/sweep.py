"""A `-m` sweep's side of a run: which (category, fold) cells a sweep expands to (for meshseg's sweeper,
hydra_plugins/meshseg_sweeper), a job's `job k/N` progress, and what a job knows of the Hydra app it runs
in (its overrides, its sweep, its log files)."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from meshseg.data.datasets import build_dataset
from meshseg.job import build_method, check_config, resolve_fold
from meshseg.timing import time_left

log = logging.getLogger("meshseg.run")

#: set by meshseg's sweeper for its jobs: how many there are and when the sweep began (time.time())
SWEEP_JOBS, SWEEP_START = "MESHSEG_SWEEP_JOBS", "MESHSEG_SWEEP_START"
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
    """{"sweep_id": the sweep's folder name} for a job of a `-m` sweep, so its runs can be found together."""
    from hydra.core.hydra_config import HydraConfig

    return {"sweep_id": Path(HydraConfig.get().sweep.dir).name} if in_sweep() else {}


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
