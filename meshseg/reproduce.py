"""`python -m meshseg.reproduce MANIFEST [overrides]`: launch the runs a manifest still lacks, then
write its report.

    python -m meshseg.reproduce experiments/table2_psb_5fold.yaml
    python -m meshseg.reproduce experiments/table2_psb_5fold.yaml report.sets=[Teddy] report.dry_run=true
    python -m meshseg.reproduce experiments/table2_psb_5fold.yaml report.columns=[3B,1B,ToG15]
    python -m meshseg.reproduce experiments/table1_psb_loo.yaml hydra/launcher=joblib   # parallel folds

Every (column, set) with folds missing becomes one `python -m meshseg.run -m` sweep over exactly those
folds, column after column (the same Hydra app, sweeper and launcher config as a hand-typed sweep:
launcher overrides pass through). Runs that exist are never launched again; an interrupted reproduce,
rerun, does the rest. Cells no run can fill (a category the dataset lacks) are listed and left alone; cells
outside a column's `sets:` (n/a) are no part of the study and never launched.
Settings: conf/reproduce.yaml (conf/report.yaml's, plus report.dry_run).
"""

from __future__ import annotations

import logging
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import hydra
from omegaconf import DictConfig

from meshseg import CONF_DIR
from meshseg.cli import ERROR_EXIT, user_errors
from meshseg.report.app import run_app
from meshseg.report.cells import Table
from meshseg.report.config import check_config, compose_config
from meshseg.report.manifest import load_manifest
from meshseg.report.publish import build, publish, summary

log = logging.getLogger("meshseg.reproduce")


@dataclass(frozen=True)
class MissingCell:
    """An incomplete (column, set) and what `meshseg.run` needs to make its missing fold runs."""

    row: str  # the set's row label
    column: str  # the column's key
    overrides: tuple[str, ...]  # the cell's run overrides (manifest, group, column, then the command line's)
    category: str  # the dataset's own name for the set
    folds: tuple[int, ...]  # the folds without a FINISHED run

    def sweep(self) -> list[str]:
        """The `python -m meshseg.run -m` arguments that make exactly the missing folds."""
        return [*self.overrides, f"category={self.category}", "fold=" + ",".join(map(str, self.folds))]


def missing_cells(table: Table) -> list[MissingCell]:
    """Every incomplete (column, set) of the table, column by column (each column's sets in table order),
    so the columns complete one after the other in the order the manifest or `report.columns` gives; a column
    with `seeds:` makes one per seed that lacks runs there (its overrides end with that seed).
    Unavailable and n/a cells (outside the column's `sets:`) are not incomplete: none is launched."""
    sets = [row for row in table.rows if row.kind == "set"]
    out = []
    for j in range(len(sets[0].cells) if sets else 0):
        for row in sets:
            c = row.cells[j]
            if c.status != "incomplete":
                continue
            if not c.missing_runs:
                out.append(MissingCell(row.label, c.column.key, tuple(c.overrides), c.category, tuple(c.missing)))
                continue
            for seed in dict.fromkeys(s for s, _ in c.missing_runs):  # a column with `seeds:`: a sweep per seed
                folds = tuple(f for s, f in c.missing_runs if s == seed)
                out.append(MissingCell(row.label, c.column.key, (*c.overrides, f"seed={seed}"), c.category, folds))
    return out


@dataclass
class Outcome:
    """What a reproduce did: the final table, the cells it launched (or would launch), those whose sweep
    failed, and the report's files and run id (None for a dry run)."""

    table: Table
    launched: list[MissingCell]
    failed: list[MissingCell]
    published: tuple[list[Path], str | None] | None


def reproduce_from_config(cfg: DictConfig) -> Outcome:
    """Launch what is missing (unless report.dry_run), then build, write and log the report."""
    check_config(cfg)
    manifest = load_manifest(cfg.manifest)
    table = build(manifest, cfg)
    for row in table.rows:
        for c in row.cells:
            if row.kind == "set" and c.status == "unavailable":
                log.warning("cannot run %s / %s: %s", row.label, c.column.key, c.problem)
    cells = missing_cells(table)
    log.info("%s: %d cell(s) lack %d fold run(s)", manifest.name, len(cells), sum(len(c.folds) for c in cells))
    if cfg.report.dry_run:
        for i, cell in enumerate(cells, 1):
            log.info("[%d/%d] would run: python -m meshseg.run -m %s", i, len(cells), shlex.join(cell.sweep()))
        return Outcome(table, cells, [], None)
    failed = []
    for i, cell in enumerate(cells, 1):
        cmd = [sys.executable, "-m", "meshseg.run", "-m", *cell.sweep()]
        log.info("[%d/%d] %s", i, len(cells), shlex.join(cmd[1:]))  # quoted: a pasted line runs as launched
        if subprocess.run(cmd).returncode != 0:
            failed.append(cell)
            log.error("sweep failed (its runs are marked FAILED in the store): %s", shlex.join(cell.sweep()))
    if cells:
        table = build(manifest, cfg)
    return Outcome(table, cells, failed, publish(table, cfg.report))


def reproduce(manifest_path, args=()) -> Outcome:
    """The command as a function: `args` as on the command line after MANIFEST."""
    return reproduce_from_config(compose_config("reproduce", manifest_path, args))


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="reproduce")
def _reproduce_app(cfg: DictConfig) -> None:
    with user_errors():
        outcome = reproduce_from_config(cfg)
    if outcome.published:
        print(summary(outcome.table, *outcome.published))
    if outcome.failed:
        sys.exit(ERROR_EXIT)  # the failed sweeps are listed above


def main(argv=None) -> None:
    """`python -m meshseg.reproduce`."""
    run_app(sys.argv[1:] if argv is None else argv, _reproduce_app, "reproduce", __doc__)


if __name__ == "__main__":
    main()
