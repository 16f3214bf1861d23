"""A manifest's table from the logged runs (DESIGN "Tracking contract").

A cell is one (column, set): the mean accuracy over all test meshes of all folds, with a percentile
bootstrap interval over those meshes. Runs are found by the config hash `meshseg.run` gives them, so
only runs made with exactly the cell's configuration (budget included) count. A cell whose folds are
not all FINISHED is incomplete and has no value. An average row is the mean of its sets' values
(the paper's way: every set weighs the same), defined only when all of them are complete. A column with
`sets:` has no cells in other sets: those are n/a (no part of the study), as is its average over a group
it covers only in part.

Every run column also gets the refinement's own effect: per set, refined minus raw (the network's argmax)
accuracy on each test mesh, with a paired bootstrap interval, so a reader sees whether the graph cut helps.

Each cell's bootstrap is seeded by the report seed and the cell's own identity (row kind, group, row label,
column key), so a cell's interval is the same whichever other rows or columns the table holds.
"""

from __future__ import annotations

import csv
import hashlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from meshseg.errors import ConfigError, MeshsegError, TrackingError
from meshseg.report.config import hydra_scope
from meshseg.report.manifest import Column, Manifest, ManifestError
from meshseg.tracking import FoldRecord


@dataclass
class Cell:
    column: Column
    published: float | None
    accs: np.ndarray | None = None  # per test mesh, %, over all folds (a complete set cell)
    scored: tuple[tuple[str, float], ...] = ()  # (test mesh, %) of every finished fold, complete or not
    gains: np.ndarray | None = None  # per test mesh, refined - raw accuracy in points (run columns only)
    meshes: tuple[str, ...] = ()  # the test mesh of each of `accs`
    folds: int = 0  # folds the split has
    missing: tuple[int, ...] = ()  # folds without a FINISHED run
    problem: str | None = None  # why no run can exist (dataset lacks the category, ...)
    budget: str | None = None
    overrides: tuple[str, ...] = ()  # what `meshseg.run` needs to make this cell's runs
    category: str | None = None  # the dataset's own name for the set
    config_hashes: tuple[str, ...] = ()  # its fold runs (the same in every store the runs are imported into)
    seconds: tuple[float, ...] = ()  # wall time of each of its fold runs (what the next runs will take)
    counts: tuple[dict[str, int], ...] = ()  # the RUN_COUNTS each of its fold runs logged (learning curves)
    outside: bool = False  # no part of the study: the column's `sets` leave this set (or part of this group) out
    members: list[Cell] = field(default_factory=list)  # an average's set cells
    value: float | None = None
    ci: tuple[float, float] | None = None

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
    def delta(self) -> float | None:
        return None if self.value is None or self.published is None else self.value - self.published

    @property
    def n_meshes(self) -> int:
        return sum(m.n_meshes for m in self.members) if self.members else 0 if self.accs is None else len(self.accs)

    def short(self) -> str:
        """An incomplete cell in a table: `— (done/folds)`, or `— (done/n sets)` for an average."""
        if self.members:
            return f"— ({sum(m.status == 'ok' for m in self.members)}/{len(self.members)} sets)"
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
        return f"{len(self.missing)} of {self.folds} folds missing"


@dataclass
class Row:
    label: str
    kind: str  # set | average | total
    group: str
    cells: list[Cell]


@dataclass
class PairedRow:
    label: str
    kind: str  # set | average | total
    n_meshes: int  # test meshes both columns scored (sets: matched by mesh id)
    value: float | None = None  # mean per-mesh difference a - b (averages: the mean over sets), points
    ci: tuple[float, float] | None = None
    why: str = ""  # why there is no value
    partial: str = ""  # a set compared on the finished folds of a column still running: which, how many


@dataclass
class Paired:
    """Two columns compared mesh by mesh: a - b per test mesh, its mean and a paired bootstrap interval."""

    a: Column
    b: Column
    rows: list[PairedRow]


@dataclass
class Table:
    manifest: Manifest
    rows: list[Row]
    overrides: tuple[str, ...]
    metric: str
    level: float
    budget_text: dict[str, str] = field(default_factory=dict)  # budget name -> what it trains on
    pairs: list[Paired] = field(default_factory=list)  # report.paired's pair, else the manifest's `paired:`
    refinement: list[tuple[Column, list[PairedRow]]] = field(default_factory=list)  # refined - raw per run column
    sets: tuple[str, ...] | None = None  # report.sets, when the table keeps only some sets
    settings: tuple[str, ...] = ()  # other report.* settings that decide which runs it lacks (report.results)

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


@dataclass
class Progress:
    """How far a table is and what fills the rest: set cells complete, fold runs missing, the command
    that makes them and the time it should take at the fold times measured so far."""

    cells_done: int
    cells: int
    runs_missing: int
    command: str
    seconds: float  # the missing runs of the timed columns, at their median fold time
    fold_seconds: dict[str, float]  # median wall time of a fold, by the label of a column that lacks runs
    untimed: tuple[str, ...]  # labels of the columns lacking runs that have no timed fold yet
    unavailable: int = 0  # set cells no run can fill here (their dataset or category is not at hand)

    def text(self) -> str:
        aside = f" ({self.unavailable} more unavailable: no data here to run them)" if self.unavailable else ""
        if not self.runs_missing:
            return f"All {self.cells} cells complete{aside}."
        line = f"{self.cells_done} of {self.cells} cells complete{aside}; {self.runs_missing} fold runs missing. "
        line += f"Next: `{self.command}`"
        if self.fold_seconds:
            per = ", ".join(f"{k} {v:.0f} s" for k, v in self.fold_seconds.items())
            took = (
                f"{self.seconds:.0f} s"
                if self.seconds < 120
                else f"{self.seconds / 60:.0f} min"
                if self.seconds < 3600
                else f"{self.seconds / 3600:.1f} h"
            )
            line += f" — about {took} on one process at the median fold time so far ({per})"
            line += f", plus the columns not timed yet: {', '.join(self.untimed)}." if self.untimed else "."
        else:
            line += " — no fold timed yet to say how long."
        return line


def progress(table: Table) -> Progress:
    """The table's Progress (set cells that runs can fill; unavailable ones left out)."""
    import shlex

    run_cells = [c for r in table.rows if r.kind == "set" for c in r.cells if c.column.predictions is None]
    cells = [c for c in run_cells if c.status in ("ok", "incomplete")]
    times: dict[str, list[float]] = {}
    for c in cells:
        times.setdefault(c.column.label, []).extend(c.seconds)
    todo = [c for c in cells if c.status == "incomplete"]
    lacking = list(dict.fromkeys(c.column.label for c in todo))
    medians = {k: float(np.median(times[k])) for k in lacking if times[k]}
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
        runs_missing=sum(len(c.missing) for c in todo),
        command=shlex.join(args),
        seconds=sum(len(c.missing) * medians[c.column.label] for c in todo if c.column.label in medians),
        fold_seconds=medians,
        untimed=tuple(k for k in lacking if k not in medians),
        unavailable=sum(c.status == "unavailable" for c in run_cells),
    )


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


def _match_category(dataset, name: str) -> str | None:
    from meshseg.data.datasets import normalise_name

    if name in dataset.categories:
        return name
    found = [c for c in dataset.categories if normalise_name(c) == normalise_name(name)]
    return found[0] if len(found) == 1 else None


class _Runs:
    """FINISHED runs of one store and experiment by config hash (the newest wins), and their per-mesh tables."""

    def __init__(self, uri: str, experiment: str):
        from mlflow import MlflowClient

        from meshseg.tracking import store_uri

        os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # one bar per run otherwise
        self.client = MlflowClient(tracking_uri=store_uri(uri))
        exp = self.client.get_experiment_by_name(experiment)
        self.by_hash: dict[str, object] = {}
        if exp is None:
            return
        token = None
        while True:
            page = self.client.search_runs(
                [exp.experiment_id], "attributes.status = 'FINISHED'", max_results=1000, page_token=token
            )
            for r in page:
                h = r.data.tags.get("config_hash")
                if h and (h not in self.by_hash or r.info.end_time > self.by_hash[h].info.end_time):
                    self.by_hash[h] = r
            token = page.token
            if not token:
                break

    def mesh_accuracies(self, run) -> list[tuple[str, dict[str, float]]]:
        """(mesh id, {metric: accuracy in %} for every FoldRecord.MESH_METRICS) of each test mesh of the run,
        from its per-mesh table (FoldRecord.PER_MESH)."""
        try:
            with tempfile.TemporaryDirectory() as tmp:
                path = self.client.download_artifacts(run.info.run_id, FoldRecord.PER_MESH, tmp)
                with open(path, newline="") as f:
                    return [
                        (row["mesh"], {m: 100.0 * float(row[m]) for m in FoldRecord.MESH_METRICS})
                        for row in csv.DictReader(f)
                    ]
        except Exception as e:  # a FINISHED run without a readable table is damage in the store, not a missing fold
            raise TrackingError(
                f"run {run.info.run_id} ({run.info.run_name}): cannot read {'/'.join(FoldRecord.MESH_METRICS)} from "
                f"{FoldRecord.PER_MESH}: {type(e).__name__}: {e}"
            ) from None


def _fill(cell: Cell, category: str, dataset, split, resolved: dict, runs: _Runs, metric: str) -> None:
    """Find a cell's category and folds, the FINISHED run of each fold by config hash, and, when
    none is missing, the per-mesh accuracies; or say why the cell cannot have runs."""
    from meshseg.data.splits import folds_for
    from meshseg.tracking import fold_identity

    cell.category = _match_category(dataset, category)
    if cell.category is None:
        cell.problem = f"dataset {dataset.name} has no category {category!r}"
        return
    try:
        folds = folds_for(dataset, cell.category, split)
    except (MeshsegError, ValueError) as e:  # the split cannot be made here (data code reports that as ValueError)
        cell.problem = str(e)
        return
    found, missing = [], []
    for fold in folds:
        _, chash = fold_identity(resolved, cell.category, fold, dataset.data_hash)
        run = runs.by_hash.get(chash)
        if run is None:
            missing.append(fold.index)
        else:
            found.append(run)
    cell.folds, cell.missing = len(folds), tuple(missing)
    cell.config_hashes = tuple(r.data.tags["config_hash"] for r in found)
    cell.seconds = tuple((r.info.end_time - r.info.start_time) / 1000 for r in found if r.info.end_time)
    cell.counts = tuple(_run_counts(r) for r in found)
    scored = [pair for r in found for pair in runs.mesh_accuracies(r)]
    cell.scored = tuple((m, float(a[metric])) for m, a in scored)  # a paired comparison uses what there is
    if not missing:
        cell.meshes, cell.accs = tuple(m for m, _ in scored), np.array([a[metric] for _, a in scored])
        cell.gains = np.array([a["acc"] - a["acc_raw"] for _, a in scored])


#: count params (`n_*`) of a fold run that learning curves read (n_train_distinct: only runs made since it exists)
RUN_COUNTS = ("n_train_samples", "n_train_distinct", "n_epochs")


def _run_counts(run) -> dict[str, int]:
    return {k: int(run.data.params[k]) for k in RUN_COUNTS if k in run.data.params}


def _fill_predictions(cell: Cell, category: str, dataset, split, spec, cache_dir: str) -> None:
    """A predictions column's cell: every test mesh of the split's folds scored from its labelling on disk."""
    from meshseg.data.splits import folds_for
    from meshseg.report.predictions import score

    cell.category = _match_category(dataset, category)
    if cell.category is None:
        cell.problem = f"dataset {dataset.name} has no category {category!r}"
        return
    folds = folds_for(dataset, cell.category, split)
    cell.folds = len(folds)
    scored = score(spec, dataset, cell.category, [m for f in folds for m in f.test], cache_dir)
    cell.meshes, cell.accs = tuple(m for m, _ in scored), np.array([a for _, a in scored])
    cell.scored = tuple((m, float(a)) for m, a in scored)


def collect(
    manifest: Manifest,
    overrides=(),
    *,
    metric: str = "acc",
    n_boot: int = 2000,
    level: float = 0.95,
    seed: int = 0,
    sets=None,
    paired=None,
) -> Table:
    """Build the table of `manifest` from the runs in the store the composed config names.

    `overrides` are run overrides applied after the manifest's (e.g. budget=cpu, tracking.uri=...);
    `sets` keeps only the rows whose name or category is listed (their groups lose the average row);
    `metric` is a per-mesh column (FoldRecord.MESH_METRICS); `paired` the columns to compare mesh by mesh:
    two column keys, or a list of such pairs (None: the manifest's `paired:` list)."""
    from hydra import compose
    from hydra.errors import HydraException

    from meshseg.data.datasets import build_dataset

    if metric not in FoldRecord.MESH_METRICS:
        raise ConfigError(f"report.metric={metric} is not allowed: choose one of {list(FoldRecord.MESH_METRICS)}")
    keep = _kept_sets(manifest, sets)
    stores: dict[tuple[str, str], _Runs] = {}
    datasets: dict[str, object] = {}
    rows: list[Row] = []
    budget_text: dict[str, str] = {}
    with hydra_scope():
        for group in manifest.groups:
            chosen = [s for s in group.sets if keep is None or s.name in keep or s.category in keep]
            if not chosen:
                continue
            grid = [[_new_cell(c, s, j) for j, c in enumerate(manifest.columns)] for s in chosen]
            for j, column in enumerate(manifest.columns):
                if column.overrides is None:
                    continue
                over = [*manifest.cell_overrides(group, column), *overrides]
                try:
                    cfg = compose("run", overrides=over)
                except HydraException as e:
                    raise _compose_error(e, manifest, group, column, overrides) from None
                _add_budget_text(budget_text, cfg.budget)
                key = (cfg.tracking.uri, cfg.tracking.experiment)
                if key not in stores:
                    stores[key] = _Runs(*key)
                runs = stores[key]
                dkey = OmegaConf.to_yaml(cfg.dataset)
                if dkey not in datasets:
                    try:
                        datasets[dkey] = build_dataset(cfg.dataset)
                    except (MeshsegError, OSError, ValueError) as e:  # no such data here: its cells say so
                        datasets[dkey] = f"dataset {cfg.dataset._target_.rsplit('.', 1)[-1]} unavailable: {e}"
                dataset = datasets[dkey]
                resolved = OmegaConf.to_container(cfg, resolve=True)  # once per column, not per fold
                for s, cell in zip(chosen, (row[j] for row in grid)):
                    if cell.outside:
                        continue
                    cell.budget, cell.overrides = cfg.budget.name, tuple(over)
                    if isinstance(dataset, str):
                        cell.problem = dataset
                    elif column.predictions is not None:
                        _fill_predictions(cell, s.category, dataset, cfg.split, column.predictions, cfg.paths.cache_dir)
                    else:
                        _fill(cell, s.category, dataset, cfg.split, resolved, runs, metric)
            rows += _group_rows(manifest, group, chosen, grid, n_boot, level, seed)
    if manifest.total and keep is None:
        every = [r.cells for r in rows if r.kind == "set"]
        total_id = ("total", "", manifest.total)
        cells = _averages(manifest, every, manifest.published_total, n_boot, level, seed, total_id)
        rows.append(Row(manifest.total, "total", "", cells))
    table = Table(manifest, rows, tuple(overrides), metric, level, budget_text)
    table.sets = None if sets is None else tuple(str(s) for s in sets)
    table.pairs = [compare(table, a, b, n_boot=n_boot, seed=seed) for a, b in _pairs_asked(manifest, paired)]
    table.refinement = [
        (c, refinement_gain(table, c.key, n_boot=n_boot, seed=seed))
        for c in table.columns
        if c.overrides is not None and c.predictions is None
    ]
    return table


def _add_budget_text(texts: dict[str, str], b) -> None:
    """What budget `b` trains on, under its name; columns that override part of one budget (a study's
    budget.faces_per_mesh=4000) add their own text beside the others, so the header names every one."""
    text = f"{b.faces_per_mesh or 'every'} training faces per mesh, {b.epochs} epochs"
    if text not in texts.get(b.name, "").split(" | "):
        texts[b.name] = f"{texts[b.name]} | {text}" if b.name in texts else text


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


def _new_cell(column: Column, s, j: int) -> Cell:
    """An empty cell of (column, set `s`); one outside the column's `sets` keeps no published number either."""
    if column.runs_on(s.name):
        return Cell(column, s.published[j])
    return Cell(column, None, outside=True)


def _group_rows(manifest: Manifest, group, chosen, grid, n_boot, level, seed) -> list[Row]:
    """A group's set rows (each complete cell's value and interval computed), then its average row when the
    group has one and every set of it is in the table."""
    rows = []
    for s, cells in zip(chosen, grid):
        for cell in cells:
            if cell.status == "ok":
                cell.value = float(cell.accs.mean())
                rng = cell_rng(seed, "set", group.name, s.name, cell.column.key)
                cell.ci = bootstrap_ci([cell.accs], n_boot, level, rng)
        rows.append(Row(s.name, "set", group.name, cells))
    if group.average and len(chosen) == len(group.sets):
        row_id = ("average", group.name, group.average)
        cells = _averages(manifest, [r.cells for r in rows], group.published_average, n_boot, level, seed, row_id)
        rows.append(Row(group.average, "average", group.name, cells))
    return rows


def _pairs_asked(manifest: Manifest, paired) -> list[tuple[str, str]]:
    """The column pairs to compare: `paired` (one pair of keys, or a list of pairs) or the manifest's."""
    if paired is None:
        return [tuple(p) for p in manifest.paired]
    paired = list(paired)
    if len(paired) == 2 and all(isinstance(k, str) for k in paired):
        return [(paired[0], paired[1])]
    return [(a, b) for a, b in paired]


def compare(table: Table, a: str, b: str, *, n_boot: int = 2000, seed: int = 0) -> Paired:
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
        if "unavailable" in (ca.status, cb.status) or not (ca.scored and cb.scored):
            return f"{a}: {ca.status}, {b}: {cb.status}"
        acc_b = dict(cb.scored)
        d = np.array([x - acc_b[m] for m, x in ca.scored if m in acc_b])
        partial = ", ".join(
            f"{c.column.key} {c.folds - len(c.missing)} of {c.folds} folds" for c in (ca, cb) if c.missing
        )
        return (d, partial) if len(d) else "no test mesh in common"

    rows = _paired_rows(table, differences, ("paired", a, b), n_boot, seed)
    return Paired(table.columns[ia], table.columns[ib], rows)


def refinement_gain(table: Table, key: str, *, n_boot: int = 2000, seed: int = 0) -> list[PairedRow]:
    """What the refinement adds in run column `key`: refined minus raw accuracy per test mesh, per set its
    mean with a paired bootstrap interval, per average row the mean over its sets."""
    j = [c.key for c in table.columns].index(key)

    def differences(row: Row) -> np.ndarray | str:
        cell = row.cells[j]
        if cell.status != "ok":
            return cell.status
        return "no raw accuracies" if cell.gains is None else cell.gains

    return _paired_rows(table, differences, ("refinement", key), n_boot, seed)


def _paired_rows(table: Table, differences, ident: tuple[str, ...], n_boot: int, seed: int) -> list[PairedRow]:
    """One PairedRow per table row from `differences(set row)` (per-mesh differences, with what makes them
    partial, or why there are none; None leaves the set out of the comparison); an average row is the mean
    over its sets compared, defined when every one of them has differences in full, and labelled with how
    many of its sets those are when some were left out."""
    out, diffs, compared = [], {}, set()
    for row in table.rows:
        rng = cell_rng(seed, *ident[:1], row.kind, row.group, row.label, *ident[1:])
        if row.kind == "set":
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
            ci = bootstrap_ci([d], n_boot, table.level, rng)
            out.append(PairedRow(row.label, row.kind, len(d), float(d.mean()), ci, partial=partial))
        else:
            members = [r for r in table.rows if r.kind == "set" and (row.kind == "total" or r.group == row.group)]
            kept = [r for r in members if (r.group, r.label) in compared]
            if kept:
                label = row.label if len(kept) == len(members) else f"{row.label} ({len(kept)} of {len(members)} sets)"
                ds = [diffs.get((r.group, r.label)) for r in kept]
                out.append(_paired_average(label, row.kind, ds, n_boot, table.level, rng))
    return out


def _paired_average(label: str, kind: str, ds: list, n_boot: int, level: float, rng) -> PairedRow:
    """The mean over sets of per-mesh differences (None: a set not compared in full), each set resampled on its own."""
    if any(d is None for d in ds) or not ds:
        return PairedRow(label, kind, 0, why="not every set compared")
    value = float(np.mean([d.mean() for d in ds]))
    return PairedRow(label, kind, sum(map(len, ds)), value, bootstrap_ci(ds, n_boot, level, rng))


def _compose_error(e: Exception, manifest: Manifest, group, column: Column, overrides) -> Exception:
    """What to say when a cell's run config cannot be composed: the command line's run overrides are at fault
    when the manifest's own overrides compose without them (a ConfigError), else the manifest (a ManifestError)."""
    from hydra import compose
    from hydra.errors import HydraException

    why = " ".join(str(e).split("\nConfig search path")[0].split())  # one line, without Hydra's search path
    where = f"group {group.name}, column {column.key}"
    if overrides:
        try:
            compose("run", overrides=manifest.cell_overrides(group, column))
        except HydraException:
            pass
        else:
            return ConfigError(f"run overrides {' '.join(overrides)} do not apply to {manifest.path} {where}: {why}")
    return ManifestError(manifest.path, f"{where}: {why}")


def _averages(
    manifest, set_cells: list[list[Cell]], published, n_boot, level, seed, row_id: tuple[str, ...]
) -> list[Cell]:
    """One average cell per column over the given set rows: the mean of the set values (each set
    weighs the same, as in the paper), its interval resampling meshes within every set. `row_id`
    (kind, group, label) with the column key seeds each cell's bootstrap. A column n/a on any of the sets has
    no average over them (the mean of part of the sets is not the paper's average): n/a too."""
    out = []
    for j, column in enumerate(manifest.columns):
        members = [cells[j] for cells in set_cells]
        if any(m.outside for m in members):
            out.append(Cell(column, None, outside=True))
            continue
        cell = Cell(
            column, published[j], members=members if column.overrides is not None else [], budget=members[0].budget
        )
        if cell.status == "ok":
            cell.value = float(np.mean([m.value for m in members]))
            cell.ci = bootstrap_ci([m.accs for m in members], n_boot, level, cell_rng(seed, *row_id, column.key))
        out.append(cell)
    return out
