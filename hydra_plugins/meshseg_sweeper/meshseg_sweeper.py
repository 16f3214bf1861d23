"""Hydra's basic sweeper, plus: a job whose overrides do not fix `category` runs every category of
its dataset, and one that does not fix `fold` every fold of its split (folds differ per category
under leave-one-out, so this is not a Cartesian product Hydra could express).

Every job's settings are checked before the first job starts; a bad one ends the sweep with one
`error:` line. Jobs that fail with a user error (bad data) are listed one line each after the sweep,
which then exits non-zero; any other failure keeps its traceback.
"""

import math
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf


@dataclass
class MeshsegSweeperConf:
    _target_: str = "hydra_plugins.meshseg_sweeper.meshseg_sweeper.MeshsegSweeper"
    max_batch_size: int | None = None
    params: dict[str, str] | None = None


ConfigStore.instance().store(group="hydra/sweeper", name="meshseg", node=MeshsegSweeperConf, provider="meshseg")


def summary(returns: list[Sequence[JobReturn]], failed: list[JobReturn], seconds: float) -> str:
    """The sweep's closing lines: jobs ran / skipped / failed, and the mean test accuracy per category."""
    done = [r.return_value for batch in returns for r in batch if r.status == JobStatus.COMPLETED]
    done = [d for d in done if isinstance(d, dict) and "acc" in d]  # meshseg.run's Outcome
    ran = sum(not d["skipped"] for d in done)
    lines = [f"sweep: {ran} ran, {len(done) - ran} skipped, {len(failed)} failed in {seconds / 60:.1f} min"]
    by_category: dict[str, list[float]] = {}
    for d in done:
        if not math.isnan(d["acc"]):
            by_category.setdefault(d["category"], []).append(d["acc"])
    if by_category:
        means = [f"{c} {100 * sum(a) / len(a):.2f} ({len(a)} folds)" for c, a in by_category.items()]
        lines.append("sweep: mean test/acc by category (fold means, %): " + ", ".join(means))
    return "\n".join(lines)


class MeshsegSweeper(BasicSweeper):
    def split_arguments(self, overrides: list[Override], max_batch_size: int | None) -> list[list[list[str]]]:
        from meshseg.cli import user_errors
        from meshseg.sweep import sweep_cells

        jobs = []
        for combo in BasicSweeper.split_arguments(overrides, None)[0]:
            keys = {o.split("=", 1)[0].lstrip("+~") for o in combo}
            with user_errors():
                cfg = self.hydra_context.config_loader.load_sweep_config(self.config, list(combo))
                cells = sweep_cells(cfg, "category" in keys, "fold" in keys)
            for category, fold in cells:
                jobs.append(
                    [
                        *combo,
                        *([f"category={category}"] if category is not None else []),
                        *([f"fold={fold}"] if fold is not None else []),
                    ]
                )
        return list(BasicSweeper.split_overrides_to_chunks(jobs, max_batch_size))

    def sweep(self, arguments: list[str]) -> Any:
        """BasicSweeper.sweep, except that failed jobs are gathered and reported together at the end
        (the basic sweeper re-raises the first with a traceback, whatever it was)."""
        from meshseg.errors import MeshsegError

        params_conf = self._parse_config()
        params_conf.extend(arguments)
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        self.overrides = self.split_arguments(parser.parse_overrides(params_conf), self.max_batch_size)
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")

        returns: list[Sequence[JobReturn]] = []
        failed: list[JobReturn] = []
        initial_job_idx = 0
        t0 = time.perf_counter()
        from meshseg.sweep import SWEEP_JOBS, SWEEP_START

        # each job logs `job k/N` with the time left (meshseg.sweep.job_progress); launchers pass the environment on
        os.environ[SWEEP_JOBS], os.environ[SWEEP_START] = str(sum(map(len, self.overrides))), f"{time.time():.3f}"
        while not self.is_done():
            batch = self.get_job_batch()
            self.validate_batch_is_legal(batch)
            try:
                results = self.launcher.launch(batch, initial_job_idx=initial_job_idx)
            except Exception as e:  # submitit: a job left the queue without a result (scancel, time limit)
                if type(e).__name__ not in ("UncompletedJobError", "FailedJobError"):
                    raise
                sys.exit(
                    f"error: {str(e).strip().splitlines()[0]}\nsweep: a cluster job ended without a result "
                    f"(cancelled, or killed at its time limit); jobs still queued go on; the runs it began are "
                    f"KILLED in the store; a rerun retries them"
                )
            failed.extend(r for r in results if r.status != JobStatus.COMPLETED)
            initial_job_idx += len(batch)
            returns.append(results)
        print(summary(returns, failed, time.perf_counter() - t0), file=sys.stderr, flush=True)
        if failed:
            other = [r for r in failed if not isinstance(r._return_value, MeshsegError)]
            if other:
                _ = other[0].return_value  # a programming error: Hydra prints its traceback
            lines = [f"error: job {' '.join(r.overrides or [])}: {r._return_value}" for r in failed]
            n = sum(len(b) for b in returns)
            sys.exit(
                "\n".join(lines) + f"\nsweep: {len(failed)} of {n} jobs failed "
                f"({time.perf_counter() - t0:.0f} s); runs they began are FAILED in the store; a rerun retries them"
            )
        return returns
