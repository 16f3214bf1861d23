"""A study manifest (experiments/*.yaml): which runs make each cell of one paper table or figure,
and the published numbers beside them, as frozen dataclasses. The schema is in experiments/README.md.

`load_manifest` is the one place a manifest is checked: each part is read by its own function, which says
what is wrong with it (`Invalid`), and every problem reaches the user as one ManifestError naming the file."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import yaml

from meshseg.errors import ConfigError, ManifestError
from meshseg.report.schema import Invalid, known

#: formats of predictions on disk a column can score (`predictions: {path, format}`)
PREDICTION_FORMATS = ("psb_labels",)
#: what a learning curve's x counts per fold run (`curves: {x: ...}`; meshseg/report/curves.py)
CURVE_X = ("samples", "distinct")
#: the keys each part of a manifest takes (experiments/README.md's schema); any other is refused
MANIFEST_KEYS = (
    *("name", "title", "source", "note", "compared_with", "overrides"),
    *("columns", "paired", "curves", "groups", "total"),
)
COLUMN_KEYS = ("key", "label", "overrides", "predictions", "sets", "seeds")
GROUP_KEYS = ("name", "overrides", "average", "published_average", "also_average", "sets")
SET_KEYS = ("name", "category", "published", "test_meshes")


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
    seeds: tuple[int, ...] | None = None  # training seeds each fold is run at (None: the run config's one seed)

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
    #: more average rows, each over part of the group's sets: (label, set names), printed after `average`
    also_average: tuple[tuple[str, tuple[str, ...]], ...] = ()


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
            raise ConfigError(
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


def _overrides(value, where: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(o, str) and "=" in o for o in value):
        raise Invalid(f"{where}: overrides must be a list of key=value strings, got {value!r}")
    return tuple(value)


def _numbers(value, n: int, where: str) -> tuple[float | None, ...]:
    if value is None:
        return (None,) * n
    if not isinstance(value, list) or len(value) != n:
        raise Invalid(f"{where}: expected a list of {n} numbers (one per column, null for none), got {value!r}")
    for v in value:
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise Invalid(f"{where}: {v!r} is not a number")
        if v is not None and not math.isfinite(v):
            raise Invalid(f"{where}: {v!r} is not a finite number (null: no published number)")
    return tuple(None if v is None else float(v) for v in value)


def _predictions(value, key: str) -> Predictions | None:
    if value is None:
        return None
    if isinstance(value, dict):
        known(value, ("path", "format"), f"column {key}, predictions: ", "predictions")
    if not isinstance(value, dict) or set(value) != {"path", "format"} or value["format"] not in PREDICTION_FORMATS:
        raise Invalid(f"column {key}: predictions must be {{path: ..., format: one of {PREDICTION_FORMATS}}}")
    return Predictions(str(value["path"]), str(value["format"]))


def _column(value, i: int) -> Column:
    """One entry of `columns:` (its `sets:` are read once the sets are known: _restricted)."""
    if not isinstance(value, dict) or not {"key", "label"} <= set(value):
        raise Invalid(f"columns[{i}]: needs key and label")
    known(value, COLUMN_KEYS, f"column {value['key']}: ", "a column")
    over = value.get("overrides")
    over = None if over is None else _overrides(over, f"column {value['key']}")
    pred = _predictions(value.get("predictions"), value["key"])
    if pred is not None:
        over = over or ()  # scored from disk, yet a run config says which dataset and split
    seeds = _seeds(value.get("seeds"), value["key"], over is None or pred is not None)
    return Column(str(value["key"]), str(value["label"]), over, pred, seeds=seeds)


def _seeds(value, key: str, no_runs: bool) -> tuple[int, ...] | None:
    """A column's `seeds:`: distinct whole numbers >= 0, on a column of runs."""
    if value is None:
        return None
    if no_runs:
        raise Invalid(f"column {key}: seeds: only a column of runs has training seeds")
    ok = isinstance(value, list) and value and all(isinstance(x, int) and not isinstance(x, bool) for x in value)
    if not ok or min(value) < 0 or len(set(value)) != len(value):
        raise Invalid(f"column {key}: seeds: give a list of distinct whole numbers >= 0, not {value!r}")
    return tuple(value)


def _columns(value) -> tuple[Column, ...]:
    columns = tuple(_column(c, i) for i, c in enumerate(value or []))
    if not columns or len({c.key for c in columns}) != len(columns):
        raise Invalid("columns must be a non-empty list with distinct keys")
    return columns


def _set(value, n: int, group: str) -> Set:
    if not isinstance(value, dict) or "name" not in value:
        raise Invalid(f"group {group}: each set needs a name")
    name = value["name"]
    known(value, SET_KEYS, f"group {group}, set {name}: ", "a set")
    published = _numbers(value.get("published"), n, f"set {name} published")
    return Set(str(name), str(value.get("category", name)), published, value.get("test_meshes"))


def _group(value, i: int, n: int) -> Group:
    if not isinstance(value, dict):
        raise Invalid(f"groups[{i}]: a group is a mapping with name and sets, got {value!r}")
    name = str(value.get("name", "?"))
    known(value, GROUP_KEYS, f"group {name}: ", "a group")
    sets = tuple(_set(s, n, name) for s in value.get("sets") or [])
    if not sets:
        raise Invalid(f"group {name} has no sets")
    return Group(
        name,
        _overrides(value.get("overrides"), f"group {name}"),
        sets,
        value.get("average"),
        _numbers(value.get("published_average"), n, f"group {name} published_average"),
        _also_average(value.get("also_average"), name, sets),
    )


def _also_average(value, group: str, sets: tuple[Set, ...]) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """A group's `also_average: [{label, sets: [names of its sets]}]`: each an average row over those sets only
    (e.g. the sets a choice was not made on); the sets in the group's order."""
    if value is None:
        return ()
    for v in value if isinstance(value, list) else ():
        if isinstance(v, dict):
            known(v, ("label", "sets"), f"group {group}, also_average {v.get('label')}: ", "an also_average row")
    shape = isinstance(value, list) and all(isinstance(v, dict) and set(v) == {"label", "sets"} for v in value)
    if not shape:
        raise Invalid(f"group {group}: also_average must be a list of {{label: ..., sets: [names]}}, got {value!r}")
    names = [s.name for s in sets]
    out = []
    for v in value:
        given = [str(x) for x in v["sets"]] if isinstance(v["sets"], list) else []
        unknown = [x for x in given if x not in names]
        if not given or unknown:
            raise Invalid(
                f"group {group}, also_average {v['label']}: sets {unknown or v['sets']!r} are not sets of the group; "
                f"its sets: {', '.join(names)}"
            )
        out.append((str(v["label"]), tuple(x for x in names if x in given)))
    if len({label for label, _ in out}) != len(out):
        raise Invalid(f"group {group}: also_average labels must be distinct")
    return tuple(out)


def _labels(groups: tuple[Group, ...], total) -> None:
    """Each row label names one row of its group: two sets of one name would pool their meshes into both cells,
    an average row named as a set reads as that set. The total row's label is no other row's. Groups may repeat
    each other's labels, as the paper's Table 3 does (a set Vases and a row Average in each of its blocks)."""
    every: dict[str, str] = {}
    for g in groups:
        rows = [(s.name, "a set") for s in g.sets] + [(str(x), "an also_average row") for x, _ in g.also_average]
        rows += [(str(g.average), "the average row")] if g.average is not None else []
        seen: dict[str, str] = {}
        for label, what in rows:
            if label in seen:
                both = f"{seen[label]} and {what} are both labelled"
                both = "two sets are named" if seen[label] == what == "a set" else both
                raise Invalid(f"group {g.name}: {both} {label!r}; each row of a group needs its own label")
            seen[label] = what
            every.setdefault(label, f"{what} of group {g.name}")
    if total is not None and str(total) in every:
        raise Invalid(f"total: the total row and {every[str(total)]} are both labelled {str(total)!r}")


def _restricted(columns: tuple[Column, ...], sets: dict, groups: tuple[Group, ...]) -> tuple[Column, ...]:
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
            raise Invalid(f"column {c.key}: sets must be a non-empty list of set names, got {given!r}")
        unknown = [str(n) for n in given if str(n) not in names]
        if unknown:
            its_sets = ", ".join(s.name for g in groups for s in g.sets)
            raise Invalid(f"column {c.key}: sets {unknown} name no set of the manifest; its sets: {its_sets}")
        out.append(replace(c, sets=tuple(dict.fromkeys(s for n in given for s in names[str(n)]))))
    return tuple(out)


def _keys(value, keys: list[str], where: str) -> tuple[str, ...]:
    """A list of column keys of the manifest."""
    if not isinstance(value, list) or not value:
        raise Invalid(f"{where}: expected a list of column keys, got {value!r}")
    unknown = [str(k) for k in value if str(k) not in keys]
    if unknown:
        raise Invalid(f"{where}: {unknown} name no column; the columns are {', '.join(keys)}")
    return tuple(str(k) for k in value)


def _pairs(value, keys: list[str]) -> tuple[tuple[str, str], ...]:
    """`paired:`, a list of [a, b] column-key pairs."""
    if value is None:
        return ()
    if not isinstance(value, list):
        raise Invalid(f"paired: expected a list of [a, b] column-key pairs, got {value!r}")
    pairs = tuple(_keys(p, keys, f"paired {p}") for p in value)
    bad = [list(p) for p in pairs if len(p) != 2]
    if bad:
        raise Invalid(f"paired: {bad} are not pairs [a, b] of column keys")
    same = [list(p) for p in pairs if p[0] == p[1]]
    if same:
        raise Invalid(f"paired: {same} pair a column with itself; a pair is two different columns [a, b]")
    return pairs


def _curves(value, keys: list[str]) -> Curves | None:
    """`curves: {x: samples|distinct, series: {name: [column keys in order of increasing budget]}}`."""
    if value is None:
        return None
    if isinstance(value, dict):
        known(value, ("x", "series"), "curves: ", "curves")
    if not isinstance(value, dict) or set(value) != {"x", "series"} or value["x"] not in CURVE_X:
        raise Invalid(f"curves: expected {{x: one of {CURVE_X}, series: {{name: [column keys]}}}}")
    series = value["series"]
    if not isinstance(series, dict) or not series:
        raise Invalid(f"curves: series must map names to lists of column keys, got {series!r}")
    return Curves(value["x"], tuple((str(n), _keys(ks, keys, f"curves series {n}")) for n, ks in series.items()))


def _document(path: Path) -> dict:
    """The manifest file's YAML mapping, with the keys every manifest has."""
    if not path.is_file():
        shipped = sorted((Path(__file__).resolve().parents[2] / "experiments").glob("*.yaml"))
        names = ", ".join(f"experiments/{p.name}" for p in shipped)
        raise Invalid("no such manifest file" + (f"; the shipped manifests: {names}" if names else ""))
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise Invalid(f"not UTF-8 text: byte {e.object[e.start]:#04x} at offset {e.start}") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise Invalid(f"not valid YAML: {e}") from None
    if not isinstance(doc, dict):
        raise Invalid("a manifest is a mapping with name, columns and groups")
    if "claims" in doc:
        raise Invalid(
            "a claims file, not a study manifest (meshseg.report judges its claims on the manifests it names)"
        )
    known(doc, MANIFEST_KEYS, "", "a manifest")
    missing = [k for k in ("name", "title", "columns", "groups") if k not in doc]
    if missing:
        raise Invalid(f"missing key(s) {missing}")
    if doc["name"] != path.stem:
        raise Invalid(f"name {doc['name']!r} differs from the file name {path.stem!r}")
    return doc


def _manifest(doc: dict, path: Path) -> Manifest:
    columns = _columns(doc["columns"])
    n = len(columns)
    groups = tuple(_group(g, i, n) for i, g in enumerate(doc["groups"] or []))
    if not groups:
        raise Invalid("no groups")
    total = doc.get("total") or {}
    if not isinstance(total, dict):
        raise Invalid(f"total: expected {{label: ..., published: [numbers]}}, got {total!r}")
    known(total, ("label", "published"), "total: ", "total")
    _labels(groups, total.get("label"))
    restrict = {str(c["key"]): c.get("sets") for c in doc["columns"]}
    columns = _restricted(columns, restrict, groups)
    keys = [c.key for c in columns]
    return Manifest(
        str(doc["name"]),
        str(doc["title"]),
        str(doc.get("source", "")),
        str(doc.get("note", "") or "").strip(),
        _overrides(doc.get("overrides"), "manifest"),
        columns,
        groups,
        total.get("label"),
        _numbers(total.get("published"), n, "total published"),
        path,
        str(doc.get("compared_with", "Published")),
        _pairs(doc.get("paired"), keys),
        _curves(doc.get("curves"), keys),
    )


def load_manifest(path: str | Path) -> Manifest:
    """Read and check a manifest; every problem is one ManifestError naming the file."""
    path = Path(path)
    try:
        return _manifest(_document(path), path)
    except Invalid as e:
        raise ManifestError(f"{path}: {e}") from None
