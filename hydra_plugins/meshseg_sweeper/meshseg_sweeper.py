"""Hydra's basic sweeper, plus: a job whose overrides do not fix `category` runs every category of
its dataset, and one that does not fix `fold` every fold of its split (folds differ per category
under leave-one-out, so this is not a Cartesian product Hydra could express).

Every job's settings are checked before the first job starts; a bad one ends the sweep with one
`error:` line. Then the sweep's parent run is made, or found again when the sweep ran before
(meshseg.sweep.SweepParent): the fold runs are nested under it, and it ends with the sweep's summary.
Jobs that fail with a user error (bad data) are listed one line each after the sweep, which then
exits non-zero; any other failure keeps its traceback.
"""

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


class MeshsegSweeper(BasicSweeper):
    def split_arguments(self, overrides: list[Override], max_batch_size: int | None) -> list[list[list[str]]]:
        from meshseg.cli import user_errors
        from meshseg.sweep import sweep_cells

        jobs = []
        self.trackings = []  # each combination's tracking settings: where the sweep's parent run goes
        for combo in BasicSweeper.split_arguments(overrides, None)[0]:
            keys = {o.split("=", 1)[0].lstrip("+~") for o in combo}
            with user_errors():
                cfg = self.hydra_context.config_loader.load_sweep_config(self.config, list(combo))
                cells = sweep_cells(cfg, "category" in keys, "fold" in keys)
            self.trackings.append(cfg.tracking)
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
        from meshseg.sweep import SWEEP_JOBS, SWEEP_START, SweepParent

        params_conf = self._parse_config()
        params_conf.extend(arguments)
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        self.overrides = self.split_arguments(parser.parse_overrides(params_conf), self.max_batch_size)
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")

        # each job logs `job k/N` with the time left (meshseg.sweep.job_progress); launchers pass the environment on
        os.environ[SWEEP_JOBS], os.environ[SWEEP_START] = str(sum(map(len, self.overrides))), f"{time.time():.3f}"
        parent = SweepParent.open(self.trackings, params_conf)
        try:
            return self._launch_all(parent)
        except BaseException as e:  # interrupted (KILLED), or a cluster job lost and a failed job reported (FAILED)
            if parent is not None:
                parent.close(None, "KILLED" if isinstance(e, KeyboardInterrupt) else "FAILED")
            raise

    def _launch_all(self, parent) -> Any:
        from meshseg.errors import MeshsegError
        from meshseg.sweep import SweepSummary

        returns: list[Sequence[JobReturn]] = []
        failed: list[JobReturn] = []
        initial_job_idx = 0
        t0 = time.perf_counter()
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
        outcomes = [r.return_value for batch in returns for r in batch if r.status == JobStatus.COMPLETED]
        summary = SweepSummary.of(outcomes, len(failed), time.perf_counter() - t0)
        print(summary.lines(), file=sys.stderr, flush=True)
        if parent is not None:
            parent.close(summary, "FAILED" if failed else "FINISHED")
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
