"""The statistics of a study table, as pure functions over its per-mesh frame (Table.meshes; one row per
test mesh of every finished fold run of every cell).

A set cell is the mean accuracy over all test meshes of all folds, with a percentile bootstrap interval over
those meshes. An average is the mean of its sets' values (the paper's way: every set weighs the same), its
interval resampling the meshes within every set, defined only when every set is complete. A paired block is
column a minus column b on the same test meshes (matched by mesh id); the refinement's block is refined minus
raw accuracy on each test mesh of one column.

Each interval is seeded by the report seed and the cell's own identity (row kind, group, row label, column
key), so a cell's interval is the same whichever other rows or columns the table holds.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from meshseg.errors import ConfigError
from meshseg.report.cells import Cell, Paired, PairedRow, Row, Table
from meshseg.report.manifest import Column


def bootstrap_ci(samples: list[np.ndarray], n_boot: int, level: float, rng: np.random.Generator) -> tuple[float, float]:
    """Percentile interval of the mean of per-set means, resampling the meshes of each set with
    replacement (one set: the plain bootstrap of a mean)."""
    stats = np.zeros(n_boot)
    for a in samples:
        a = np.asarray(a, np.float64)
        stats += a[rng.integers(0, len(a), size=(n_boot, len(a)))].mean(axis=1)
    stats /= len(samples)
    lo, hi = np.quantile(stats, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def cell_rng(seed: int, *identity: str) -> np.random.Generator:
    """The bootstrap generator of one cell: the report seed and the cell's identity (e.g. row kind, group,
    row label, column key) hashed into 32-bit words, so that no other cell's presence changes it."""
    digest = hashlib.sha256("\x1f".join(identity).encode()).digest()
    return np.random.default_rng([seed, *np.frombuffer(digest[:16], dtype="<u4").tolist()])


@dataclass(frozen=True)
class Bootstrap:
    """How every interval of a table is drawn: resamples, coverage, and the seed each cell's identity extends."""

    n_boot: int = 2000
    level: float = 0.95
    seed: int = 0

    def interval(self, samples: list[np.ndarray], *identity: str) -> tuple[float, float]:
        return bootstrap_ci(samples, self.n_boot, self.level, cell_rng(self.seed, *identity))


# --- per-mesh values of one cell ---------------------------------------------------------------------------


def cell_meshes(meshes: pd.DataFrame, row: Row, key: str) -> pd.DataFrame:
    """The per-mesh rows of one (row, column key): every test mesh of the cell's finished fold runs, in fold order."""
    return meshes[(meshes["group"] == row.group) & (meshes["row"] == row.label) & (meshes["column"] == key)]


def scored(meshes: pd.DataFrame, row: Row, key: str, metric: str) -> dict[str, float]:
    """{mesh id: accuracy in %} of the cell's finished folds, complete or not."""
    own = cell_meshes(meshes, row, key)
    return dict(zip(own["mesh"], own[metric].to_numpy()))


def _pairs(meshes: pd.DataFrame, row: Row, key: str, metric: str) -> list[tuple[str, float]]:
    own = cell_meshes(meshes, row, key)
    return list(zip(own["mesh"], own[metric].to_numpy()))


def accuracies(meshes: pd.DataFrame, row: Row, key: str, metric: str) -> np.ndarray:
    """The cell's per-mesh accuracies (%), in fold order (a complete cell's sample)."""
    return np.array(cell_meshes(meshes, row, key)[metric].to_numpy(), dtype=np.float64)


def gains(meshes: pd.DataFrame, row: Row, key: str) -> np.ndarray | None:
    """Refined minus raw accuracy per test mesh; None where the column has no raw accuracies (scored from disk)."""
    own = cell_meshes(meshes, row, key)
    raw = np.array(own["acc_raw"].to_numpy(), dtype=np.float64)
    return None if np.isnan(raw).any() else np.array(own["acc"].to_numpy(), dtype=np.float64) - raw


def paired_differences(meshes: pd.DataFrame, row: Row, a: str, b: str, metric: str) -> np.ndarray:
    """a - b on each test mesh both cells scored, in a's order."""
    acc_b = scored(meshes, row, b, metric)
    return np.array([x - acc_b[m] for m, x in _pairs(meshes, row, a, metric) if m in acc_b])


# --- cells ---------------------------------------------------------------------------------------------------


def set_cell(cell: Cell, sample: np.ndarray, boot: Bootstrap, identity: Sequence[str]) -> Cell:
    """A complete set cell's value and interval from its per-mesh accuracies; any other cell as it is."""
    if cell.status != "ok":
        return cell
    return replace(cell, value=float(sample.mean()), ci=boot.interval([sample], *identity), n_meshes=len(sample))


def average_cell(
    column: Column,
    published: float | None,
    members: Sequence[Cell],
    samples: Sequence[np.ndarray],
    boot: Bootstrap,
    identity: Sequence[str],
) -> Cell:
    """One column's average over set cells `members` (their per-mesh `samples`): the mean of the set values
    (each set weighs the same, as in the paper), its interval resampling meshes within every set and seeded by
    `identity`. A column n/a on any of the sets has no average over them (the mean of part of the sets is not
    the paper's average): n/a too."""
    if any(m.outside for m in members):
        return Cell(column, None, outside=True)
    runs = tuple(members) if column.overrides is not None else ()
    cell = Cell(column, published, n_meshes=sum(m.n_meshes for m in runs), budget=members[0].budget, members=runs)
    if cell.status != "ok":
        return cell
    return replace(cell, value=float(np.mean([m.value for m in members])), ci=boot.interval(list(samples), *identity))


def average_row(table: Table, label: str, kind: str, members: Sequence[Row], published, boot: Bootstrap) -> Row:
    """The average row (kind average or total) over the set rows `members`, one cell per column; each cell's
    interval seeded by (kind, group, label, column key)."""
    group = members[0].group if kind == "average" else ""
    cells = []
    for j, column in enumerate(table.columns):
        cells_j = [r.cells[j] for r in members]
        samples = [accuracies(table.meshes, r, column.key, table.metric) for r in members]
        cells.append(average_cell(column, published[j], cells_j, samples, boot, (kind, group, label, column.key)))
    return Row(label, kind, group, tuple(cells))


# --- paired blocks -----------------------------------------------------------------------------------------


def compare(table: Table, a: str, b: str, boot: Bootstrap) -> Paired:
    """Column `a` minus column `b` on the same test meshes (matched by mesh id): per set the mean difference
    with a paired bootstrap interval (the meshes resampled, each keeping both its accuracies), per average
    row the mean over its sets (each set resampled on its own). A set whose cell is still incomplete is
    compared on the meshes of its finished folds, marked partial; an average needs every set complete. A set
    where either column is n/a is no part of the comparison: an average is then over the sets both have."""
    keys = [c.key for c in table.columns]
    for key in (a, b):
        if key not in keys:
            raise ConfigError(f"report.paired: {key!r} is no column of {table.manifest.name}; its columns are {keys}")
    ia, ib = keys.index(a), keys.index(b)

    def differences(row: Row) -> tuple[np.ndarray, str] | str | None:
        ca, cb = row.cells[ia], row.cells[ib]
        if "n/a" in (ca.status, cb.status):
            return None
        unscored = any(cell_meshes(table.meshes, row, k).empty for k in (a, b))
        if "unavailable" in (ca.status, cb.status) or unscored:
            return f"{a}: {ca.status}, {b}: {cb.status}"
        d = paired_differences(table.meshes, row, a, b, table.metric)
        partial = ", ".join(
            f"{c.column.key} {c.folds - len(c.missing)} of {c.folds} folds" for c in (ca, cb) if c.missing
        )
        return (d, partial) if len(d) else "no test mesh in common"

    rows = paired_rows(table, differences, ("paired", a, b), boot)
    return Paired(table.columns[ia], table.columns[ib], rows)


def refinement_gain(table: Table, key: str, boot: Bootstrap) -> tuple[PairedRow, ...]:
    """What the refinement adds in run column `key`: refined minus raw accuracy per test mesh, per set its
    mean with a paired bootstrap interval, per average row the mean over its sets."""
    j = [c.key for c in table.columns].index(key)

    def differences(row: Row) -> np.ndarray | str:
        if row.cells[j].status != "ok":
            return row.cells[j].status
        d = gains(table.meshes, row, key)
        return "no raw accuracies" if d is None else d

    return paired_rows(table, differences, ("refinement", key), boot)


def paired_rows(table: Table, differences, ident: tuple[str, ...], boot: Bootstrap) -> tuple[PairedRow, ...]:
    """One PairedRow per table row from `differences(set row)` (per-mesh differences, with what makes them
    partial, or why there are none; None leaves the set out of the comparison); an average row is the mean
    over its sets compared, defined when every one of them has differences in full, and labelled with how
    many of its sets those are when some were left out."""
    out, diffs, compared = [], {}, set()
    for row in table.rows:
        identity = (*ident[:1], row.kind, row.group, row.label, *ident[1:])
        if row.kind != "set":
            members = [
                r
                for r in table.rows
                if r.kind == "set"
                and (row.kind == "total" or r.group == row.group)
                and (not row.sets or r.label in row.sets)
            ]
            kept = [r for r in members if (r.group, r.label) in compared]
            if kept:
                label = row.label if len(kept) == len(members) else f"{row.label} ({len(kept)} of {len(members)} sets)"
                ds = [diffs.get((r.group, r.label)) for r in kept]
                out.append(_paired_average(label, row.kind, ds, boot, identity))
            continue
        d = differences(row)
        if d is None:
            continue
        compared.add((row.group, row.label))
        if isinstance(d, str):
            out.append(PairedRow(row.label, row.kind, 0, why=d))
            continue
        d, partial = d if isinstance(d, tuple) else (d, "")
        if not partial:
            diffs[(row.group, row.label)] = d
        out.append(
            PairedRow(row.label, row.kind, len(d), float(d.mean()), boot.interval([d], *identity), partial=partial)
        )
    return tuple(out)


def _paired_average(label: str, kind: str, ds: list, boot: Bootstrap, identity: tuple[str, ...]) -> PairedRow:
    """The mean over sets of per-mesh differences (None: a set not compared in full), each set resampled on its own."""
    if any(d is None for d in ds) or not ds:
        return PairedRow(label, kind, 0, why="not every set compared")
    value = float(np.mean([d.mean() for d in ds]))
    return PairedRow(label, kind, sum(map(len, ds)), value, boot.interval(ds, *identity))
