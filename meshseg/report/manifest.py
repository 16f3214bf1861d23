"""A study manifest (experiments/*.yaml): which runs make each cell of one paper table or figure,
and the published numbers beside them. The schema is in experiments/README.md."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import yaml

from meshseg import errors


class ManifestError(errors.ManifestError):
    """A manifest that cannot be used; the message names the file and the problem."""

    def __init__(self, path, problem: str):
        super().__init__(f"{path}: {problem}")


#: formats of predictions on disk a column can score (`predictions: {path, format}`)
PREDICTION_FORMATS = ("psb_labels",)
#: what a learning curve's x counts per fold run (`curves: {x: ...}`; meshseg/report/curves.py)
CURVE_X = ("samples", "distinct")


@dataclass(frozen=True)
class Predictions:
    """Labellings on disk, one file per mesh, scored like a run's predictions (e.g. Kalogerakis 2010's)."""

    path: str  # a folder or an archive (unpacked once into the cache)
    format: str  # psb_labels: `<id>.lab`, L-PSB's `<id>_labels.txt` format (label name, then 1-based faces)


@dataclass(frozen=True)
class Column:
    key: str
    label: str
    overrides: tuple[str, ...] | None  # None: the paper's number only, no runs (e.g. ShapePFCN)
    predictions: Predictions | None = None  # scored from disk instead of from runs
    sets: tuple[str, ...] | None = None  # names of the only sets it has runs for (None: all); its other cells are n/a

    def runs_on(self, set_name: str) -> bool:
        """Whether the (column, set) cell is part of the study."""
        return self.sets is None or set_name in self.sets


@dataclass(frozen=True)
class Curves:
    """A learning-curve figure: accuracy against the training the cells' runs saw (`x`: CURVE_X)."""

    x: str
    series: tuple[tuple[str, tuple[str, ...]], ...]  # (name, column keys in order of increasing budget)


@dataclass(frozen=True)
class Set:
    name: str  # the row label as printed
    category: str  # the dataset's category
    published: tuple[float | None, ...]
    test_meshes: int | None = None


@dataclass(frozen=True)
class Group:
    name: str
    overrides: tuple[str, ...]
    sets: tuple[Set, ...]
    average: str | None  # label of the group's average row, None: no such row
    published_average: tuple[float | None, ...]


@dataclass(frozen=True)
class Manifest:
    name: str
    title: str
    source: str
    note: str
    overrides: tuple[str, ...]
    columns: tuple[Column, ...]
    groups: tuple[Group, ...]
    total: str | None  # label of the average over every set of every group
    published_total: tuple[float | None, ...]
    path: Path
    #: what the `published` numbers are: "Published" (the paper's) or e.g. "Reference" (a pinned run's)
    compared_with: str = "Published"
    paired: tuple[tuple[str, str], ...] = ()  # column pairs (a, b) the report compares mesh by mesh, a - b
    curves: Curves | None = None

    def only_columns(self, keys) -> Manifest:
        """The manifest with only the columns `keys` (in that order), their published numbers with them."""
        index = {c.key: j for j, c in enumerate(self.columns)}
        unknown = [k for k in keys if k not in index]
        if unknown or len(set(keys)) != len(keys) or not keys:
            raise errors.ConfigError(
                f"report.columns={list(keys)}: give distinct column keys of {self.name}: {', '.join(index)}"
            )
        pick = [index[k] for k in keys]

        def sliced(values: tuple) -> tuple:
            return tuple(values[j] for j in pick)

        groups = tuple(
            replace(
                g,
                sets=tuple(replace(s, published=sliced(s.published)) for s in g.sets),
                published_average=sliced(g.published_average),
            )
            for g in self.groups
        )
        columns = tuple(self.columns[j] for j in pick)
        paired = tuple(p for p in self.paired if set(p) <= set(keys))  # a pair loses meaning with either column
        curves = self.curves
        if curves is not None:
            series = tuple((n, kept) for n, ks in curves.series if (kept := tuple(k for k in ks if k in keys)))
            curves = replace(curves, series=series) if series else None
        return replace(
            self,
            columns=columns,
            groups=groups,
            published_total=sliced(self.published_total),
            paired=paired,
            curves=curves,
        )

    def cell_overrides(self, group: Group, column: Column) -> list[str]:
        """Run overrides of one (group, column): the manifest's, then the group's, then the column's."""
        return [*self.overrides, *group.overrides, *(column.overrides or ())]


def _overrides(value, path, where: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(o, str) and "=" in o for o in value):
        raise ManifestError(path, f"{where}: overrides must be a list of key=value strings, got {value!r}")
    return tuple(value)


def _numbers(value, n: int, path, where: str) -> tuple[float | None, ...]:
    if value is None:
        return (None,) * n
    if not isinstance(value, list) or len(value) != n:
        raise ManifestError(
            path, f"{where}: expected a list of {n} numbers (one per column, null for none), got {value!r}"
        )
    for v in value:
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ManifestError(path, f"{where}: {v!r} is not a number")
    return tuple(None if v is None else float(v) for v in value)


def _restricted(columns: list[Column], sets: dict, groups: list[Group], path) -> list[Column]:
    """The columns with their `sets:` (given as {key: list}) as the manifest's set names. A set may be named
    by its name or its category, as report.sets takes it (budget_study's `FourLeg` is the set `Fourleg`)."""
    names: dict[str, list[str]] = {}
    for g in groups:
        for s in g.sets:
            for name in dict.fromkeys((s.name, s.category)):
                names.setdefault(name, []).append(s.name)
    out = []
    for c in columns:
        given = sets.get(c.key)
        if given is None:
            out.append(c)
            continue
        if not isinstance(given, list) or not given:
            raise ManifestError(path, f"column {c.key}: sets must be a non-empty list of set names, got {given!r}")
        unknown = [str(n) for n in given if str(n) not in names]
        if unknown:
            known = ", ".join(s.name for g in groups for s in g.sets)
            raise ManifestError(path, f"column {c.key}: sets {unknown} name no set of the manifest; its sets: {known}")
        out.append(replace(c, sets=tuple(dict.fromkeys(s for n in given for s in names[str(n)]))))
    return out


def _keys(value, keys: list[str], path, where: str) -> tuple[str, ...]:
    """A list of column keys of the manifest."""
    if not isinstance(value, list) or not value:
        raise ManifestError(path, f"{where}: expected a list of column keys, got {value!r}")
    unknown = [str(k) for k in value if str(k) not in keys]
    if unknown:
        raise ManifestError(path, f"{where}: {unknown} name no column; the columns are {', '.join(keys)}")
    return tuple(str(k) for k in value)


def _pairs(value, keys: list[str], path) -> tuple[tuple[str, str], ...]:
    """`paired:`, a list of [a, b] column-key pairs."""
    if value is None:
        return ()
    if not isinstance(value, list):
        raise ManifestError(path, f"paired: expected a list of [a, b] column-key pairs, got {value!r}")
    pairs = tuple(_keys(p, keys, path, f"paired {p}") for p in value)
    bad = [list(p) for p in pairs if len(p) != 2]
    if bad:
        raise ManifestError(path, f"paired: {bad} are not pairs [a, b] of column keys")
    return pairs


def _curves(value, keys: list[str], path) -> Curves | None:
    """`curves: {x: samples|distinct, series: {name: [column keys in order of increasing budget]}}`."""
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) != {"x", "series"} or value["x"] not in CURVE_X:
        raise ManifestError(path, f"curves: expected {{x: one of {CURVE_X}, series: {{name: [column keys]}}}}")
    series = value["series"]
    if not isinstance(series, dict) or not series:
        raise ManifestError(path, f"curves: series must map names to lists of column keys, got {series!r}")
    return Curves(value["x"], tuple((str(n), _keys(ks, keys, path, f"curves series {n}")) for n, ks in series.items()))


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a manifest; every problem is reported with the file's name."""
    path = Path(path)
    if not path.is_file():
        shipped = sorted((Path(__file__).resolve().parents[2] / "experiments").glob("*.yaml"))
        known = ", ".join(f"experiments/{p.name}" for p in shipped)
        raise ManifestError(path, "no such manifest file" + (f"; the shipped manifests: {known}" if known else ""))
    try:
        doc = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ManifestError(path, f"not valid YAML: {e}") from None
    if not isinstance(doc, dict):
        raise ManifestError(path, "a manifest is a mapping with name, columns and groups")
    missing = [k for k in ("name", "title", "columns", "groups") if k not in doc]
    if missing:
        raise ManifestError(path, f"missing key(s) {missing}")
    if doc["name"] != path.stem:
        raise ManifestError(path, f"name {doc['name']!r} differs from the file name {path.stem!r}")
    columns, restrict = [], {}
    for i, c in enumerate(doc["columns"] or []):
        if not isinstance(c, dict) or not {"key", "label"} <= set(c):
            raise ManifestError(path, f"columns[{i}]: needs key and label")
        over = c.get("overrides")
        over = None if over is None else _overrides(over, path, f"column {c['key']}")
        pred = c.get("predictions")
        if pred is not None:
            if (
                not isinstance(pred, dict)
                or set(pred) != {"path", "format"}
                or pred["format"] not in PREDICTION_FORMATS
            ):
                raise ManifestError(
                    path, f"column {c['key']}: predictions must be {{path: ..., format: one of {PREDICTION_FORMATS}}}"
                )
            pred, over = Predictions(str(pred["path"]), str(pred["format"])), over or ()
        columns.append(Column(str(c["key"]), str(c["label"]), over, pred))
        restrict[str(c["key"])] = c.get("sets")
    if not columns or len({c.key for c in columns}) != len(columns):
        raise ManifestError(path, "columns must be a non-empty list with distinct keys")
    n = len(columns)
    groups = []
    for g in doc["groups"] or []:
        gname = str(g.get("name", "?"))
        sets = []
        for s in g.get("sets") or []:
            if not isinstance(s, dict) or "name" not in s:
                raise ManifestError(path, f"group {gname}: each set needs a name")
            sets.append(
                Set(
                    str(s["name"]),
                    str(s.get("category", s["name"])),
                    _numbers(s.get("published"), n, path, f"set {s['name']} published"),
                    s.get("test_meshes"),
                )
            )
        if not sets:
            raise ManifestError(path, f"group {gname} has no sets")
        groups.append(
            Group(
                gname,
                _overrides(g.get("overrides"), path, f"group {gname}"),
                tuple(sets),
                g.get("average"),
                _numbers(g.get("published_average"), n, path, f"group {gname} published_average"),
            )
        )
    if not groups:
        raise ManifestError(path, "no groups")
    columns = _restricted(columns, restrict, groups, path)
    keys = [c.key for c in columns]
    total = doc.get("total") or {}
    return Manifest(
        str(doc["name"]),
        str(doc["title"]),
        str(doc.get("source", "")),
        str(doc.get("note", "") or "").strip(),
        _overrides(doc.get("overrides"), path, "manifest"),
        tuple(columns),
        tuple(groups),
        total.get("label"),
        _numbers(total.get("published"), n, path, "total published"),
        path,
        str(doc.get("compared_with", "Published")),
        _pairs(doc.get("paired"), keys, path),
        _curves(doc.get("curves"), keys, path),
    )
