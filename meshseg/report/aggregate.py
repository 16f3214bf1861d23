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

import functools
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


def nested_stats(
    folds: list[tuple[np.ndarray, np.ndarray | None]], n_boot: int, rng: np.random.Generator
) -> np.ndarray:
    """Bootstrap replicates of one set's mean a − b (or a, where b is None) resampling what varies between
    runs: each column's training seeds (rows of its (seeds, meshes) arrays, drawn apart for a and b), then
    whole folds, then the test meshes within each drawn fold. A replicate is the mean over every drawn mesh of
    (mean of a over a's drawn seeds − mean of b over b's), so with one seed and one mesh a fold it is the
    mesh-level bootstrap, and seeds that agree leave it as it is (the draws use their own streams)."""
    seed_rng, fold_rng, mesh_rng = rng.spawn(3)

    @functools.cache  # one draw per column (a, b) and seed count: a partial cell's folds may hold fewer seeds
    def seed_weights(side: str, s: int) -> np.ndarray:  # (n_boot, s): how often each seed is drawn, over s
        draws = seed_rng.integers(0, s, size=(n_boot, s))
        return np.stack([(draws == i).sum(axis=1) for i in range(s)], axis=1) / s

    per_fold = [  # (n_boot, meshes) each
        seed_weights("a", len(a)) @ a - (0 if b is None else seed_weights("b", len(b)) @ b) for a, b in folds
    ]
    picks = fold_rng.integers(0, len(folds), size=(n_boot, len(folds)))
    total, count = np.zeros(n_boot), np.zeros(n_boot)
    for j in range(len(folds)):
        for f, d in enumerate(per_fold):
            rows = np.flatnonzero(picks[:, j] == f)
            m = d.shape[1]
            draw = mesh_rng.integers(0, m, size=(len(rows), m))
            total[rows] += np.take_along_axis(d[rows], draw, axis=1).sum(axis=1)
            count[rows] += m
    return total / count


def nested_interval(
    sets: list[list[tuple[np.ndarray, np.ndarray | None]]], n_boot: int, level: float, rng: np.random.Generator
) -> tuple[float, float]:
    """Percentile interval of the mean over sets of each set's mean a − b, each set resampled by nested_stats
    on its own (its folds: (a, b) arrays of shape (seeds, test meshes of the fold)). Where every fold holds one
    test mesh and every column one seed (leave-one-out, one seed), that is the mesh-level bootstrap, and the
    interval is bootstrap_ci's with the same generator, to the last digit."""
    if all(x is None or x.shape == (1, 1) for folds in sets for pair in folds for x in pair):
        flat = [np.array([a[0, 0] - (0 if b is None else b[0, 0]) for a, b in folds]) for folds in sets]
        return bootstrap_ci(flat, n_boot, level, rng)
    stats = np.mean([nested_stats(folds, n_boot, rng) for folds in sets], axis=0)
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

    def nested(self, sets: list[list[tuple[np.ndarray, np.ndarray | None]]], *identity: str) -> tuple[float, float]:
        """nested_interval (seeds, folds, then meshes resampled) with this bootstrap's settings."""
        return nested_interval(sets, self.n_boot, self.level, cell_rng(self.seed, *identity))


# --- per-mesh values of one cell ---------------------------------------------------------------------------


def cell_meshes(meshes: pd.DataFrame, row: Row, key: str) -> pd.DataFrame:
    """The per-mesh rows of one (row, column key): every test mesh of the cell's finished fold runs, in fold order."""
    return meshes[(meshes["group"] == row.group) & (meshes["row"] == row.label) & (meshes["column"] == key)]


def mesh_means(own: pd.DataFrame, metric: str) -> np.ndarray:
    """Per test mesh of one cell's rows (`own`), its accuracy averaged over the training seeds it was tested
    at, in fold order (first appearance): with one seed, the rows' own values."""
    return own.groupby("mesh", sort=False)[metric].mean().to_numpy(dtype=np.float64)


def _by_mesh(meshes: pd.DataFrame, row: Row, key: str, metric: str) -> pd.Series:
    own = cell_meshes(meshes, row, key)
    return own.groupby("mesh", sort=False)[metric].mean()


def scored(meshes: pd.DataFrame, row: Row, key: str, metric: str) -> dict[str, float]:
    """{mesh id: accuracy in % (mean over its seeds)} of the cell's finished folds, complete or not."""
    return _by_mesh(meshes, row, key, metric).to_dict()


def _pairs(meshes: pd.DataFrame, row: Row, key: str, metric: str) -> list[tuple[str, float]]:
    return list(_by_mesh(meshes, row, key, metric).items())


def accuracies(meshes: pd.DataFrame, row: Row, key: str, metric: str) -> np.ndarray:
    """The cell's per-mesh accuracies (%; each the mean over its seeds), in fold order (a complete cell's sample)."""
    return mesh_means(cell_meshes(meshes, row, key), metric)


def gains(meshes: pd.DataFrame, row: Row, key: str) -> np.ndarray | None:
    """Refined minus raw accuracy per test mesh (mean over its seeds); None where the column has no raw
    accuracies (scored from disk)."""
    own = cell_meshes(meshes, row, key)
    if own["acc_raw"].isna().any():
        return None
    return mesh_means(own.assign(gain=own["acc"] - own["acc_raw"]), "gain")


def paired_differences(meshes: pd.DataFrame, row: Row, a: str, b: str, metric: str) -> np.ndarray:
    """a - b on each test mesh both cells scored, in a's order."""
    acc_b = scored(meshes, row, b, metric)
    return np.array([x - acc_b[m] for m, x in _pairs(meshes, row, a, metric) if m in acc_b])


def fold_arrays(meshes: pd.DataFrame, row: Row, key: str, metric: str) -> dict[int, pd.DataFrame]:
    """The cell's per-mesh values by fold, each a (seeds x test meshes) frame (rows: the training seeds its
    runs have, `seed` 0 where the frame names none, ascending; columns: mesh ids, sorted; NaN where a seed lacks
    a mesh). `metric` "gain" is refined minus raw."""
    own = cell_meshes(meshes, row, key)
    values = (own["acc"] - own["acc_raw"] if metric == "gain" else own[metric]).to_numpy(np.float64)
    seeds = own["seed"].to_numpy() if "seed" in own else np.zeros(len(own), int)
    # plain dicts, not a pivot per fold: a leave-one-out table asks for thousands of these
    cells: dict[int, dict[tuple[int, str], list[float]]] = {}
    for f, s, m, v in zip(own["fold"].to_numpy(), seeds, own["mesh"].to_numpy(), values):
        cells.setdefault(int(f), {}).setdefault((int(s), m), []).append(v)
    out = {}
    for f in sorted(cells):
        by = cells[f]
        rows, cols = sorted({s for s, _ in by}), sorted({m for _, m in by})
        at_row, at_col = {s: i for i, s in enumerate(rows)}, {m: j for j, m in enumerate(cols)}
        grid = np.full((len(rows), len(cols)), np.nan)
        for (s, m), vs in by.items():
            grid[at_row[s], at_col[m]] = np.mean(vs)
        out[f] = pd.DataFrame(grid, index=pd.Index(rows, name="seed"), columns=pd.Index(cols, name="mesh"))
    return out


def nested_units(meshes: pd.DataFrame, row: Row, a: str, b: str | None, metric: str, offset: float = 0.0):
    """One set's folds for nested_stats: per fold (a's (seeds, meshes) array, b's or None) over the test meshes
    both columns scored in it (b None: a alone, less `offset`, e.g. a published number; metric "gain": the
    refinement's own gain in column a)."""
    fa = fold_arrays(meshes, row, a, metric)
    fb = fold_arrays(meshes, row, b, metric) if b is not None else {}
    out = []
    for f, xa in fa.items():
        if b is None:
            out.append((xa.to_numpy() - offset, None))
            continue
        if f not in fb:
            continue
        both = [m for m in xa.columns if m in fb[f].columns]
        if both:
            out.append((xa[both].to_numpy(), fb[f][both].to_numpy()))
    return out


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
    value, ci = float(np.mean([m.value for m in members])), boot.interval(list(samples), *identity)
    per_seed = {len(m.seed_values) for m in members}
    seeds = (
        np.mean([m.seed_values for m in members], axis=0) if per_seed == {max(per_seed)} and max(per_seed) > 1 else ()
    )
    return replace(cell, value=value, ci=ci, seed_values=tuple(float(v) for v in seeds))


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
        units = nested_units(table.meshes, row, a, b, table.metric)
        return (d, units, partial) if len(d) else "no test mesh in common"

    rows = paired_rows(table, differences, ("paired", a, b), boot)
    return Paired(table.columns[ia], table.columns[ib], rows)


def refinement_gain(table: Table, key: str, boot: Bootstrap) -> tuple[PairedRow, ...]:
    """What the refinement adds in run column `key`: refined minus raw accuracy per test mesh, per set its
    mean with a paired bootstrap interval, per average row the mean over its sets."""
    j = [c.key for c in table.columns].index(key)

    def differences(row: Row) -> tuple | str:
        if row.cells[j].status != "ok":
            return row.cells[j].status
        d = gains(table.meshes, row, key)
        return "no raw accuracies" if d is None else (d, nested_units(table.meshes, row, key, None, "gain"), "")

    return paired_rows(table, differences, ("refinement", key), boot)


def paired_rows(table: Table, differences, ident: tuple[str, ...], boot: Bootstrap) -> tuple[PairedRow, ...]:
    """One PairedRow per table row from `differences(set row)` (per-mesh differences, their folds for the nested
    interval and what makes them partial, or why there are none; None leaves the set out of the comparison);
    an average row is the mean over its sets compared, defined when every one of them has differences in
    full, and labelled with how many of its sets those are when some were left out. Intervals resample seeds,
    folds, then meshes (nested_interval: under leave-one-out with one seed, the mesh bootstrap)."""
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
        d, units, partial = d
        if not partial:
            diffs[(row.group, row.label)] = (d, units)
        out.append(
            PairedRow(row.label, row.kind, len(d), float(d.mean()), boot.nested([units], *identity), partial=partial)
        )
    return tuple(out)


def _paired_average(label: str, kind: str, ds: list, boot: Bootstrap, identity: tuple[str, ...]) -> PairedRow:
    """The mean over sets of per-mesh differences ((differences, folds) per set; None: a set not compared in
    full), each set resampled on its own."""
    if any(d is None for d in ds) or not ds:
        return PairedRow(label, kind, 0, why="not every set compared")
    value = float(np.mean([d.mean() for d, _ in ds]))
    return PairedRow(label, kind, sum(len(d) for d, _ in ds), value, boot.nested([u for _, u in ds], *identity))
