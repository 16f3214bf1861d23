"""The values a study table is made of: cells, rows, paired comparisons, the table itself and how far it is.
All immutable: meshseg/report/aggregate.py computes them from the per-mesh table of the runs, the writers
print them."""

from __future__ import annotations

import shlex
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from meshseg.report.manifest import Column, Manifest

#: the columns of a table's per-mesh frame that the statistics read (meshseg/report/runs.py adds the runs')
MESH_KEYS = ("group", "row", "column", "mesh", "acc", "acc_raw")


def no_meshes() -> pd.DataFrame:
    """A per-mesh frame without a row."""
    return pd.DataFrame({k: pd.Series(dtype=float if k.startswith("acc") else object) for k in MESH_KEYS})


@dataclass(frozen=True)
class Cell:
    """One (column, set) of a table, or a column's average over sets (`members`): what the writers print."""

    column: Column
    published: float | None
    value: float | None = None
    ci: tuple[float, float] | None = None
    n_meshes: int = 0  # test meshes its value is over (an average: those of its sets)
    folds: int = 0  # folds the split has
    missing: tuple[int, ...] = ()  # folds without a FINISHED run (at one of its seeds, or more)
    missing_runs: tuple[tuple[int, int], ...] = ()  # a column with `seeds:`: the (seed, fold) runs missing
    seeds: tuple[int, ...] = ()  # a column with `seeds:`: its training seeds
    seed_values: tuple[float, ...] = ()  # with more than one seed: the cell's value at each (its runs at that seed)
    problem: str | None = None  # why no run can exist (dataset lacks the category, ...)
    budget: str | None = None
    overrides: tuple[str, ...] = ()  # what `meshseg.run` needs to make this cell's runs
    category: str | None = None  # the dataset's own name for the set
    config_hashes: tuple[str, ...] = ()  # its fold runs (the same in every store the runs are imported into)
    seconds: tuple[float, ...] = ()  # wall time of each of its fold runs (what the next runs will take)
    counts: tuple[dict[str, int], ...] = ()  # the RUN_COUNTS each of its fold runs logged (learning curves)
    outside: bool = False  # no part of the study: the column's `sets` leave this set (or part of this group) out
    members: tuple[Cell, ...] = ()  # an average's set cells

    @property
    def status(self) -> str:
        """n/a | published | unavailable | incomplete | ok."""
        if self.outside:
            return "n/a"
        if self.column.overrides is None:
            return "published"
        if self.members:
            bad = [m.status for m in self.members]
            return "unavailable" if "unavailable" in bad else "incomplete" if "incomplete" in bad else "ok"
        return "unavailable" if self.problem else "incomplete" if self.missing else "ok"

    @property
    def seed_sd(self) -> float | None:
        """The spread between training seeds: the sd of the per-seed values (None with fewer than two)."""
        return float(np.std(self.seed_values, ddof=1)) if len(self.seed_values) > 1 else None

    @property
    def runs_missing(self) -> int:
        """Fold runs still to make: every (seed, fold) of a column with seeds, else every fold."""
        return len(self.missing_runs) or len(self.missing)

    @property
    def delta(self) -> float | None:
        return None if self.value is None or self.published is None else self.value - self.published

    def short(self) -> str:
        """An incomplete cell in a table: `— (done/folds)`, or `— (done/n sets)` for an average."""
        if self.members:
            return f"— ({sum(m.status == 'ok' for m in self.members)}/{len(self.members)} sets)"
        if self.missing_runs:
            runs = self.folds * len(self.seeds)
            return f"— ({runs - len(self.missing_runs)}/{runs} runs)"
        return f"— ({self.folds - len(self.missing)}/{self.folds})"

    def why(self) -> str:
        """What keeps an n/a, incomplete or unavailable cell from having a number."""
        if self.outside:
            return f"{self.column.key} is run on {', '.join(self.column.sets)} only"
        if self.members:
            n = sum(m.status != "ok" for m in self.members)
            return f"{n} of {len(self.members)} sets not complete"
        if self.problem:
            return self.problem
        if self.missing_runs:
            return f"{len(self.missing_runs)} of {self.folds * len(self.seeds)} fold runs missing (seeds {self.seeds})"
        return f"{len(self.missing)} of {self.folds} folds missing"


@dataclass(frozen=True)
class Row:
    label: str
    kind: str  # set | average | total
    group: str
    cells: tuple[Cell, ...]
    sets: tuple[str, ...] = ()  # an average over part of its group: those set rows (empty: all of them)


@dataclass(frozen=True)
class PairedRow:
    label: str
    kind: str  # set | average | total
    n_meshes: int  # test meshes both columns scored (sets: matched by mesh id)
    value: float | None = None  # mean per-mesh difference a - b (averages: the mean over sets), points
    ci: tuple[float, float] | None = None
    why: str = ""  # why there is no value
    partial: str = ""  # a set compared on the finished folds of a column still running: which, how many


@dataclass(frozen=True)
class Paired:
    """Two columns compared mesh by mesh: a - b per test mesh, its mean and a paired bootstrap interval."""

    a: Column
    b: Column
    rows: tuple[PairedRow, ...]


@dataclass(frozen=True)
class Table:
    manifest: Manifest
    rows: tuple[Row, ...]
    overrides: tuple[str, ...]
    metric: str
    level: float
    budget_text: dict[str, str] = field(default_factory=dict)  # budget name -> what it trains on
    pairs: tuple[Paired, ...] = ()  # report.paired's pair, else the manifest's `paired:`
    refinement: tuple[tuple[Column, tuple[PairedRow, ...]], ...] = ()  # refined - raw per run column
    sets: tuple[str, ...] | None = None  # report.sets, when the table keeps only some sets
    settings: tuple[str, ...] = ()  # other report.* settings that decide which runs it lacks (report.results)
    #: one row per test mesh of every finished fold run of every cell (group, row, column key, mesh, acc, ...)
    meshes: pd.DataFrame = field(default_factory=no_meshes)
    #: report.boundaries: where each test mesh's errors lie (meshseg/report/boundaries.py), how many test meshes
    #: had no per-face labels to read, and how many were a predictions column's under acc_raw; None: not asked
    boundaries: tuple[pd.DataFrame, int, int] | None = None

    @property
    def budgets(self) -> list[str]:
        return sorted({c.budget for r in self.rows for c in r.cells if c.budget})

    @property
    def columns(self) -> tuple[Column, ...]:
        return self.manifest.columns

    @property
    def paired(self) -> Paired | None:
        """The first paired comparison (the one report.paired names), or None."""
        return self.pairs[0] if self.pairs else None


@dataclass(frozen=True)
class Progress:
    """How far a table is and what fills the rest: set cells complete, fold runs missing, the command
    that makes them, the time it should take at the fold times measured so far, and what the runs took."""

    cells_done: int
    cells: int
    runs_missing: int
    command: str
    seconds: float  # the missing runs of the timed columns, at their set's median fold time (else the column's)
    fold_seconds: dict[str, float]  # median wall time of a fold, by the label of a column that lacks runs
    untimed: tuple[str, ...]  # labels of the columns lacking runs that have no timed fold yet
    unavailable: int = 0  # set cells no run can fill here (their dataset or category is not at hand)
    spent: dict[str, tuple[int, float]] = field(default_factory=dict)  # column label -> (timed runs, their seconds)

    def text(self) -> str:
        aside = f" ({self.unavailable} more unavailable: no data here to run them)" if self.unavailable else ""
        if not self.runs_missing:
            return f"All {self.cells} cells complete{aside}." + self.spent_text()
        line = f"{self.cells_done} of {self.cells} cells complete{aside}; {self.runs_missing} fold runs missing. "
        line += f"Next: `{self.command}`"
        if not self.fold_seconds:
            return line + " — no fold timed yet to say how long." + self.spent_text()
        per = ", ".join(f"{k} {v:.0f} s" for k, v in self.fold_seconds.items())
        line += f" — about {_duration(self.seconds)} on one process at each set's median fold time so far"
        line += f" (the column's where a set has none: {per})"
        line += f", plus the columns not timed yet: {', '.join(self.untimed)}." if self.untimed else "."
        return line + self.spent_text()

    def spent_text(self) -> str:
        """What the table's runs cost so far: each column's runs and their wall times summed (one process;
        workers side by side share the wall clock)."""
        if not self.spent:
            return ""
        each = ", ".join(f"{k} {_duration(s)} ({n} run{'s' * (n != 1)})" for k, (n, s) in self.spent.items())
        return f" Run time so far, summed over runs: {each}."


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 3600 else f"{seconds / 3600:.1f} h"


def progress(table: Table) -> Progress:
    """The table's Progress (set cells that runs can fill; unavailable ones left out)."""
    run_cells = [c for r in table.rows if r.kind == "set" for c in r.cells if c.column.predictions is None]
    cells = [c for c in run_cells if c.status in ("ok", "incomplete")]
    times: dict[str, list[float]] = {}
    for c in cells:
        times.setdefault(c.column.label, []).extend(s for s in c.seconds if np.isfinite(s))
    todo = [c for c in cells if c.status == "incomplete"]
    lacking = list(dict.fromkeys(c.column.label for c in todo))
    medians = {k: float(np.median(times[k])) for k in lacking if times[k]}

    def fold_time(c: Cell) -> float:
        # a set's own folds where it has any: sets differ several-fold (classes x boosting rounds, faces)
        own = [s for s in c.seconds if np.isfinite(s)]
        return float(np.median(own)) if own else medians[c.column.label]

    path = table.manifest.path
    try:
        path = path.resolve().relative_to(Path.cwd())
    except ValueError:
        pass
    args = ["python", "-m", "meshseg.reproduce", str(path), *table.overrides, *table.settings]
    if table.sets is not None:
        args.append(f"report.sets=[{','.join(table.sets)}]")
    return Progress(
        cells_done=len(cells) - len(todo),
        cells=len(cells),
        runs_missing=sum(c.runs_missing for c in todo),
        command=shlex.join(args),
        seconds=sum(c.runs_missing * fold_time(c) for c in todo if c.column.label in medians),
        fold_seconds=medians,
        untimed=tuple(k for k in lacking if k not in medians),
        unavailable=sum(c.status == "unavailable" for c in run_cells),
        spent={k: (len(v), float(sum(v))) for k, v in times.items() if v},
    )
