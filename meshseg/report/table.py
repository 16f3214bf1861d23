"""A manifest's table from the logged runs (DESIGN "Tracking contract"): each cell's runs planned from its run
config, the runs read into one per-mesh frame (meshseg/report/runs.py: from the store, or with collect_records
from the shipped results records), the cells and blocks computed from it (meshseg/report/aggregate.py).

A cell is one (column, set): the mean accuracy over all test meshes of all folds. A cell whose folds are not
all FINISHED is incomplete and has no value; one no run can exist for (its dataset lacks the category) is
unavailable. A column with `sets:` has no cells in other sets: those are n/a (no part of the study), as is its
average over a group it covers only in part.

Every run column also gets the refinement's own effect: per set, refined minus raw (the network's argmax)
accuracy on each test mesh, with a paired bootstrap interval, so a reader sees whether the graph cut helps.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from meshseg.config import run_config
from meshseg.errors import ConfigError, ManifestError, MeshsegError
from meshseg.report.aggregate import Bootstrap, average_row, compare, mesh_means, refinement_gain, set_cell
from meshseg.report.cells import Cell, Row, Table, no_meshes
from meshseg.report.manifest import Column, Group, Manifest, Set
from meshseg.report.runs import RUN_COLUMNS, mesh_table, records_mesh_table
from meshseg.tracking import FoldRecord


@dataclass(frozen=True)
class ColumnRun:
    """What one (group, column) takes from its run config: everything its cells' fold runs share."""

    overrides: tuple[str, ...]  # the manifest's, the group's, the column's, then the command line's
    budget: str
    store: tuple[str, str]  # (tracking uri, experiment)
    dataset: object  # the built dataset, or why it cannot be built here (a str)
    split: object
    resolved: dict  # the resolved run config (identity of its fold runs)
    cache_dir: str


@dataclass(frozen=True)
class CellPlan:
    """One (group, set, column) before its runs are read: its cell without a value, and the fold runs it needs."""

    group: str
    row: str  # the set's name
    cell: Cell  # folds, problem, budget, overrides, category (no value yet)
    run: ColumnRun | None = None  # None: a published-only column, or n/a
    folds: tuple = ()  # the split's folds (meshseg.data.splits.Fold)
    hashes: tuple[str, ...] = ()  # the config hash of each fold's run (run columns), seed by seed
    seeds: tuple[int, ...] = ()  # the training seed of each of those runs
    scores: tuple[dict, ...] = ()  # the per-mesh rows of a predictions column, scored from disk


def _match_category(dataset, name: str) -> str | None:
    from meshseg.data.datasets import normalise_name

    if name in dataset.categories:
        return name
    found = [c for c in dataset.categories if normalise_name(c) == normalise_name(name)]
    return found[0] if len(found) == 1 else None


class _Planner:
    """The cell plans of one manifest: each (group, column)'s run config composed once, each dataset built once,
    and the text of every budget the columns train on."""

    def __init__(self, manifest: Manifest, overrides):
        self.manifest, self.overrides = manifest, tuple(overrides)
        self.datasets: dict[str, object] = {}
        self.budget_text: dict[str, str] = {}

    def column_run(self, group: Group, column: Column, seed: int | None = None) -> ColumnRun:
        """The column's run config in the group (at training seed `seed`: the column's `seeds:` win over the
        command line's, as in the sweeps reproduce launches)."""
        over = (
            *self.manifest.cell_overrides(group, column),
            *self.overrides,
            *(() if seed is None else (f"seed={seed}",)),
        )
        try:
            cfg = checked_run_config(over)
        except ConfigError as e:
            raise _compose_error(e, self.manifest, group, column, self.overrides) from None
        self._add_budget_text(cfg.budget)
        return ColumnRun(
            over,
            cfg.budget.name,
            (cfg.tracking.uri, cfg.tracking.experiment),
            self._dataset(cfg.dataset),
            cfg.split,
            OmegaConf.to_container(cfg, resolve=True),  # once per column, not per fold
            cfg.paths.cache_dir,
        )

    def _dataset(self, spec) -> object:
        from meshseg.data.datasets import build_dataset

        key = OmegaConf.to_yaml(spec)
        if key not in self.datasets:
            try:
                self.datasets[key] = build_dataset(spec)
            except (MeshsegError, OSError, ValueError) as e:  # no such data here: its cells say so
                self.datasets[key] = f"dataset {spec._target_.rsplit('.', 1)[-1]} unavailable: {e}"
        return self.datasets[key]

    def _add_budget_text(self, b) -> None:
        """What budget `b` trains on, under its name; columns that override part of one budget (a study's
        budget.faces_per_mesh=4000) add their own text beside the others, so the header names every one."""
        text = f"{b.faces_per_mesh or 'every'} training faces per mesh, {b.epochs} epoch{'s' if b.epochs != 1 else ''}"
        text += f", {b.precision}" if b.get("precision") else ""  # cpu2: the 1D CNN in bf16-mixed
        texts = self.budget_text
        if text not in texts.get(b.name, "").split(" | "):
            texts[b.name] = f"{texts[b.name]} | {text}" if b.name in texts else text

    def plans(self, group: Group, sets: list[Set]) -> list[list[CellPlan]]:
        """One plan per (set, column) of the group's chosen sets, row by row."""
        grid = [[self._blank(group, s, j, c) for j, c in enumerate(self.manifest.columns)] for s in sets]
        for j, column in enumerate(self.manifest.columns):
            if column.overrides is None:
                continue
            runs = [self.column_run(group, column, seed) for seed in column.seeds or (None,)]
            for s, row in zip(sets, grid):
                if not row[j].cell.outside:
                    row[j] = _plan(row[j], runs, s.category)
        return grid

    @staticmethod
    def _blank(group: Group, s: Set, j: int, column: Column) -> CellPlan:
        """A cell of (column, set `s`) before its run config is known; one outside the column's `sets` keeps
        no published number either."""
        if column.runs_on(s.name):
            return CellPlan(group.name, s.name, Cell(column, s.published[j]))
        return CellPlan(group.name, s.name, Cell(column, None, outside=True))


def _plan(blank: CellPlan, runs: list[ColumnRun], category: str) -> CellPlan:
    """The cell's category, folds and the config hash of each fold's run at each of the column's seeds (`runs`:
    its run config at each); or why the cell cannot have runs."""
    from meshseg.data.splits import folds_for
    from meshseg.tracking import fold_identity

    run = runs[0]
    overrides = run.overrides if blank.cell.column.seeds is None else run.overrides[:-1]  # reproduce adds each seed
    cell = replace(blank.cell, budget=run.budget, overrides=overrides)
    if isinstance(run.dataset, str):
        return replace(blank, cell=replace(cell, problem=run.dataset), run=run)
    name = _match_category(run.dataset, category)
    if name is None:
        return replace(blank, cell=replace(cell, problem=f"dataset {run.dataset.name} has no category {category!r}"))
    cell = replace(cell, category=name)
    try:
        folds = tuple(folds_for(run.dataset, name, run.split))
    except MeshsegError as e:  # the split cannot be made here
        if cell.column.predictions is not None:
            raise
        return replace(blank, cell=replace(cell, problem=str(e)), run=run)
    cell = replace(cell, folds=len(folds))
    if cell.column.predictions is not None:
        return _fill_predictions(replace(blank, cell=cell, run=run, folds=folds))
    hashes = tuple(fold_identity(r.resolved, name, f, run.dataset.data_hash)[1] for r in runs for f in folds)
    seeds = tuple(int(r.resolved["seed"]) for r in runs for _ in folds)
    return replace(blank, cell=cell, run=run, folds=folds, hashes=hashes, seeds=seeds)


def _fill_predictions(plan: CellPlan) -> CellPlan:
    """A predictions column's cell with its per-mesh rows: every test mesh of the split's folds scored from its
    labelling on disk (no raw accuracy)."""
    from meshseg.report.predictions import score

    tests = [(f.index, m) for f in plan.folds for m in f.test]
    run, cell = plan.run, plan.cell
    scored = score(cell.column.predictions, run.dataset, cell.category, [m for _, m in tests], run.cache_dir)
    keys = {"group": plan.group, "row": plan.row, "column": cell.column.key, "category": cell.category}
    rows = tuple(
        {**keys, "fold": fold, "seed": 0, "mesh": m, "acc": float(a), "acc_raw": float("nan")}
        for (fold, _), (m, a) in zip(tests, scored)
    )
    return replace(plan, scores=rows)


def _meshes(plans: list[CellPlan], read) -> pd.DataFrame:
    """The per-mesh frame of every planned cell: the runs' rows as `read` finds them (_from_stores: store by
    store), then the predictions' rows."""
    wanted = pd.DataFrame(
        [
            {
                "group": p.group,
                "row": p.row,
                "column": p.cell.column.key,
                "category": p.cell.category,
                "fold": f.index,
                "seed": seed,
                "config_hash": h,
                "uri": p.run.store[0],
                "experiment": p.run.store[1],
            }
            for p in plans
            for f, seed, h in zip(p.folds * (len(p.hashes) // max(len(p.folds), 1)), p.seeds, p.hashes)
        ],
        columns=["group", "row", "column", "category", "fold", "seed", "config_hash", "uri", "experiment"],
    )
    parts = read(wanted)
    parts += [pd.DataFrame(list(p.scores)) for p in plans if p.scores]
    parts = [p for p in parts if not p.empty]
    meshes = pd.concat(parts, ignore_index=True) if parts else no_meshes()
    return meshes.reindex(columns=MESH_COLUMNS)


def _from_stores(wanted: pd.DataFrame) -> list[pd.DataFrame]:
    """The wanted fold runs from the store each one's column logs to (its uri and experiment): one search per store."""
    return [
        mesh_table(*store, part.drop(columns=["uri", "experiment"]))
        for store, part in wanted.groupby(["uri", "experiment"], sort=False)
    ]


#: the per-mesh frame's columns: the cell's keys, its fold and training seed, the run's identity, time and counts,
#: the mesh's scores
MESH_COLUMNS = [
    "group",
    "row",
    "column",
    "category",
    "fold",
    "seed",
    *RUN_COLUMNS[:4],
    "mesh",
    *FoldRecord.MESH_METRICS,
]


def _cell(plan: CellPlan, meshes: pd.DataFrame, metric: str, boot: Bootstrap) -> Cell:
    """A planned cell with what its runs say: the folds found, their times and counts, and its value."""
    own = meshes[(meshes["group"] == plan.group) & (meshes["row"] == plan.row)]
    own = own[own["column"] == plan.cell.column.key]
    cell = plan.cell
    if plan.hashes:
        runs = own.drop_duplicates("run_id")
        found = set(zip(runs["seed"], runs["fold"]))
        lacking = tuple(
            (s, f.index) for s in dict.fromkeys(plan.seeds) for f in plan.folds if (s, f.index) not in found
        )
        cell = replace(
            cell,
            missing=tuple(sorted({f for _, f in lacking})),
            missing_runs=lacking if cell.column.seeds is not None else (),
            seeds=cell.column.seeds or (),
            config_hashes=tuple(runs["config_hash"]),
            seconds=tuple(float(s) for s in runs["seconds"] if not np.isnan(s)),
            counts=tuple(runs["counts"]),
        )
    cell = set_cell(cell, mesh_means(own, metric), boot, ("set", plan.group, plan.row, cell.column.key))
    if cell.status == "ok" and len(cell.seeds) > 1:
        cell = replace(cell, seed_values=tuple(float(v) for v in own.groupby("seed", sort=True)[metric].mean()))
    return cell


def check_request(manifest: Manifest, metric: str, sets, paired) -> None:
    """report.metric, report.sets and report.paired checked against the manifest, before any store is opened."""
    if metric not in FoldRecord.MESH_METRICS:
        raise ConfigError(f"report.metric={metric} is not allowed: choose one of {list(FoldRecord.MESH_METRICS)}")
    _kept_sets(manifest, sets)
    _pairs_asked(manifest, paired)


def _kept_sets(manifest: Manifest, sets) -> set[str] | None:
    """report.sets as a set of names, each checked to name a set (by its name or category) of the manifest."""
    keep = None if sets is None else {str(s) for s in sets}
    known = {name for g in manifest.groups for s in g.sets for name in (s.name, s.category)}
    if keep is not None and not keep <= known:
        raise ConfigError(
            f"report.sets: {sorted(keep - known)} name no set of {manifest.name}; its sets are "
            f"{', '.join(s.name for g in manifest.groups for s in g.sets)}"
        )
    return keep


def _pairs_asked(manifest: Manifest, paired) -> list[tuple[str, str]]:
    """The column pairs to compare: `paired` (one pair of keys, or a list of pairs) or the manifest's."""
    if paired is None:
        return [tuple(p) for p in manifest.paired]
    paired = list(paired)
    if len(paired) == 2 and all(isinstance(k, str) for k in paired):
        return [(paired[0], paired[1])]
    return [(a, b) for a, b in paired]


def checked_run_config(overrides):
    """A cell's run config, checked as `meshseg.run` checks it before a fold (meshseg.job.check_config): a column
    no run can be made of (branches=7) is refused before the table, not offered or launched by reproduce. The
    config's own checks only: the machine's (an accelerator, bf16 on this CPU) are for where the runs are made."""
    from meshseg.job import check_config

    cfg = run_config(overrides)
    check_config(cfg)
    return cfg


def _compose_error(e: ConfigError, manifest: Manifest, group, column: Column, overrides) -> MeshsegError:
    """What to say when a cell's run config cannot be composed or checked: the command line's run overrides are at
    fault when the manifest's own overrides make a valid config without them (a ConfigError), else the manifest
    (a ManifestError)."""
    where = f"group {group.name}, column {column.key}"
    if overrides:
        try:
            checked_run_config(manifest.cell_overrides(group, column))
        except ConfigError:
            pass
        else:
            return ConfigError(f"run overrides {' '.join(overrides)} do not apply to {manifest.path} {where}: {e}")
    return ManifestError(f"{manifest.path}: {where}: {e}")


def collect(
    manifest: Manifest,
    overrides=(),
    *,
    metric: str = "acc",
    sets=None,
    paired=None,
    boot: Bootstrap | None = None,
) -> Table:
    """Build the table of `manifest` from the runs in the store the composed config names.

    `overrides` are run overrides applied after the manifest's (e.g. budget=cpu, tracking.uri=...);
    `sets` keeps only the rows whose name or category is listed (their groups lose the average row);
    `metric` is a per-mesh column (FoldRecord.MESH_METRICS); `paired` the columns to compare mesh by mesh:
    two column keys, or a list of such pairs (None: the manifest's `paired:` list); `boot` how intervals are
    drawn (None: Bootstrap's defaults)."""
    boot = boot or Bootstrap()
    return _blocks(_table(manifest, overrides, metric, sets, boot, _from_stores), paired, boot)


def fold_hashes(manifest: Manifest, overrides=(), sets=None) -> set[str]:
    """The config hashes of the fold runs the table of `manifest` (its run columns, the chosen `sets`) wants,
    found without reading a store: what a report imports of the shipped records."""
    runs = [c.key for c in manifest.columns if c.overrides is not None and c.predictions is None]
    if not runs:
        return set()
    manifest, keep = manifest.only_columns(runs), _kept_sets(manifest, sets)
    planner = _Planner(manifest, overrides)
    chosen = [(g, [s for s in g.sets if keep is None or s.name in keep or s.category in keep]) for g in manifest.groups]
    return {h for g, ss in chosen if ss for row in planner.plans(g, ss) for p in row for h in p.hashes}


def collect_records(
    root, manifest: Manifest, overrides=(), *, metric: str = "acc", sets=None, boot: Bootstrap | None = None
) -> Table:
    """collect's table with its fold runs read from the results records under `root` (e.g. results/; see
    meshseg.results) instead of a store: the table a store holding just those runs gives, without importing
    them first. Its paired blocks are the manifest's (aggregate.compare makes others)."""
    boot = boot or Bootstrap()
    read = lambda wanted: [records_mesh_table(root, wanted.drop(columns=["uri", "experiment"]))]
    return _blocks(_table(manifest, overrides, metric, sets, boot, read), None, boot)


def _table(manifest: Manifest, overrides, metric: str, sets, boot: Bootstrap, read) -> Table:
    """The table without its blocks, its runs' per-mesh rows found by `read` (see _meshes)."""
    if metric not in FoldRecord.MESH_METRICS:
        raise ConfigError(f"report.metric={metric} is not allowed: choose one of {list(FoldRecord.MESH_METRICS)}")
    keep = _kept_sets(manifest, sets)
    planner = _Planner(manifest, overrides)
    grids = {}
    for g in manifest.groups:
        chosen = [s for s in g.sets if keep is None or s.name in keep or s.category in keep]
        if chosen:
            grids[g.name] = planner.plans(g, chosen)
    meshes = _meshes([p for grid in grids.values() for row in grid for p in row], read)
    table = Table(manifest, (), tuple(overrides), metric, boot.level, planner.budget_text, meshes=meshes)
    rows: list[Row] = []
    for group in (g for g in manifest.groups if g.name in grids):
        cells = [tuple(_cell(p, meshes, metric, boot) for p in plans) for plans in grids[group.name]]
        members = [Row(s.row, "set", group.name, c) for s, c in zip((r[0] for r in grids[group.name]), cells)]
        rows += members
        if group.average and len(members) == len(group.sets):
            rows.append(average_row(table, group.average, "average", members, group.published_average, boot))
        for label, names in group.also_average:
            part = [m for m in members if m.label in names]
            if len(part) == len(names):  # not when report.sets left some of them out
                unpublished = (None,) * len(table.columns)
                rows.append(replace(average_row(table, label, "average", part, unpublished, boot), sets=names))
    if manifest.total and keep is None:
        every = [r for r in rows if r.kind == "set"]
        rows.append(average_row(table, manifest.total, "total", every, manifest.published_total, boot))
    return replace(table, rows=tuple(rows), sets=None if sets is None else tuple(str(s) for s in sets))


def _blocks(table: Table, paired, boot: Bootstrap) -> Table:
    """The table with its paired blocks and every run column's refinement block."""
    pairs = tuple(compare(table, a, b, boot) for a, b in _pairs_asked(table.manifest, paired))
    refinement = tuple(
        (c, refinement_gain(table, c.key, boot))
        for c in table.columns
        if c.overrides is not None and c.predictions is None
    )
    return replace(table, pairs=pairs, refinement=refinement)
