"""A claims file (experiments/claims.yaml): the paper's claims, each a comparison of two manifest columns,
the tables judged as a whole and the budget study's notes, read and checked (meshseg/report/claims.py judges
them on the runs)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import yaml

from meshseg.errors import ManifestError
from meshseg.report.schema import Invalid, holds_key, known

#: what a claim's `test` may be
TESTS = ("mean", "every_set", "most_sets", "equal", "refinement")
VERDICTS = ("reproduced", "contradicted", "inconclusive", "partly", "not yet run", "no data")
#: the keys a claims file, a claim, a `tables:` entry and `budget_study:` take (experiments/claims.yaml); any other
#: is refused, as a manifest's are
FILE_KEYS = ("name", "title", "rule", "overrides", "thresholds", "tables", "budget_study", "claims")
CLAIM_KEYS = ("id", "text", "source", "table", "a", "b", "test", "sets", "group", "margin", "min_share", "models")
TABLE_KEYS = ("table", "label", "group")
STUDY_KEYS = ("table", "compare", "fold_lists", "floor_table", "floor_columns")


@dataclass(frozen=True)
class Claim:
    id: str
    text: str  # the paper's sentence, quoted or closely paraphrased
    source: str  # where in the paper (section, table label)
    table: str  # the manifest (experiments/<table>.yaml) whose columns it compares
    a: str  # column key: the side the paper says is better (or the column refined, for `refinement`)
    b: str | None  # column key: the other side (None for `refinement`)
    test: str = "mean"
    sets: tuple[str, ...] | None = None  # only these sets (names as printed); None: every set of `group`
    group: str | None = None  # the manifest's group (None: its first)
    margin: float = 0.5  # `equal`: how close counts as equal, points
    min_share: float = 0.75  # `most_sets`: the share of sets that must go the claimed way
    models: tuple[str, ...] = ()  # the budget study's models its evidence rests on (1B, 3B): the budget note


@dataclass(frozen=True)
class TableSpec:
    table: str  # manifest name
    label: str  # e.g. "Table 2"
    group: str | None = None


@dataclass(frozen=True)
class ClaimsFile:
    name: str
    title: str
    rule: str
    overrides: tuple[str, ...]
    claims: tuple[Claim, ...]
    tables: tuple[TableSpec, ...]
    full: float  # a table's run columns all within this of the published averages (points): full
    partial: float  # some run column within this: partial
    # budget_study: {table, compare: {model: [(a, b), ...]}, fold_lists: {model: [a, b]}, floor_table, floor_columns}
    study: dict
    path: Path

    def tables_needed(self) -> dict[str, set[str]]:
        """{manifest name: the column keys the claims, table verdicts and budget notes read}."""
        need: dict[str, set[str]] = {}
        for c in self.claims:
            need.setdefault(c.table, set()).update(k for k in (c.a, c.b) if k)
        for t in self.tables:
            need.setdefault(t.table, set())  # every run column: filled in by the caller from the manifest
        if self.study:
            pairs = [p for ps in self.study.get("compare", {}).values() for p in ps]
            pairs += self.study.get("fold_lists", {}).values()
            need.setdefault(self.study["table"], set()).update(k for p in pairs for k in p)
            if self.study.get("floor_table"):
                need.setdefault(self.study["floor_table"], set()).update(self.study["floor_columns"].values())
        return need


def is_claims_file(path) -> bool:
    """Whether a YAML file is a claims file (a mapping with `claims:`) rather than a study manifest."""
    return holds_key(path, "claims")


def load_claims(path) -> ClaimsFile:
    """Read and check a claims file; every problem is reported with the file's name."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as e:
        raise ManifestError(f"{path}: cannot read the claims file: {e}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("claims"), list) or not doc["claims"]:
        raise ManifestError(f"{path}: a claims file is a mapping with a non-empty `claims:` list")
    try:
        return _claims_file(doc, path)
    except Invalid as e:
        raise ManifestError(f"{path}: {e}") from None


def _claims_file(doc: dict, path: Path) -> ClaimsFile:
    known(doc, FILE_KEYS, "", "a claims file")
    study = _study(doc.get("budget_study") or {})
    claims, seen = [], set()
    for i, c in enumerate(doc["claims"]):
        claims.append(_claim(c, f"claims[{i}]", study))
        if claims[-1].id in seen:
            raise Invalid(f"claims[{i}]: id {c['id']!r} is used twice")
        seen.add(claims[-1].id)
    full, partial = _thresholds(doc.get("thresholds") or {})
    return ClaimsFile(
        str(doc.get("name", path.stem)),
        str(doc.get("title", "Claims")),
        " ".join(str(doc.get("rule", "")).split()),
        _strings(doc.get("overrides") or [], "overrides", "run overrides, e.g. [budget=cpu]"),
        tuple(claims),
        _tables(doc.get("tables") or []),
        full,
        partial,
        study,
        path,
    )


def _claim(c, where: str, study: dict) -> Claim:
    if not isinstance(c, dict) or not {"id", "text", "table", "a"} <= set(c):
        raise Invalid(f"{where}: needs id, text, table and a")
    where = f"{where} ({c['id']})"
    known(c, CLAIM_KEYS, f"{where}: ", "a claim")
    test = c.get("test", "mean")
    if test not in TESTS:
        raise Invalid(f"{where}: test {test!r} is not one of {list(TESTS)}")
    if (test == "refinement") != (c.get("b") is None):
        raise Invalid(f"{where}: b is required, except with test: refinement")
    if c.get("b") is not None and str(c["a"]) == str(c["b"]):
        raise Invalid(f"{where}: a and b are both column {str(c['a'])!r}; a claim compares two columns")
    sets = c.get("sets")
    models = _strings(c.get("models") or [], f"{where}: models", "the budget study's models, e.g. [3B]")
    unknown = [m for m in models if study and m not in study.get("compare", {})]
    if unknown:
        compared = ", ".join(study.get("compare", {}))
        raise Invalid(f"{where}: models {unknown} have no budget_study.compare entry; it compares {compared}")
    return Claim(
        str(c["id"]),
        " ".join(str(c["text"]).split()),
        str(c.get("source", "")),
        str(c["table"]),
        str(c["a"]),
        None if c.get("b") is None else str(c["b"]),
        test,
        None if sets is None else _strings(sets, f"{where}: sets", "set names, e.g. [Fish, Teddy]", empty=False),
        c.get("group"),
        _points(c.get("margin", 0.5), f"{where}: margin"),
        _share(c.get("min_share", 0.75), f"{where}: min_share"),
        models,
    )


def _strings(value, where: str, what: str, empty: bool = True) -> tuple[str, ...]:
    """A list of names: a bare string would be read letter by letter (`sets: Table` as T, a, b, l, e)."""
    if not isinstance(value, list) or not (value or empty) or not all(isinstance(v, str) for v in value):
        raise Invalid(f"{where}={value!r} is not allowed: give a list of {what}")
    return tuple(value)


def _points(value, where: str) -> float:
    """A margin or threshold: a finite number of points > 0 (a negative margin turns `equal` upside down)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
        raise Invalid(f"{where}={value!r} is not allowed: it must be a number of points > 0")
    return float(value)


def _share(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= 1:
        raise Invalid(f"{where}={value!r} is not allowed: it must be a share > 0 and <= 1 (0.75: three sets in four)")
    return float(value)


def _thresholds(value) -> tuple[float, float]:
    """(full, partial): a table is fully reproduced with every run column within `full` points of the published
    averages, partly with some column within `partial`; so full <= partial."""
    if not isinstance(value, dict):
        raise Invalid(f"thresholds: expected {{full: points, partial: points}}, got {value!r}")
    known(value, ("full", "partial"), "thresholds: ", "thresholds")
    full = _points(value.get("full", 1.0), "thresholds.full")
    partial = _points(value.get("partial", 2.0), "thresholds.partial")
    if full > partial:
        raise Invalid(
            f"thresholds: full={full:g} is more than partial={partial:g}: full is the stricter threshold "
            "(every run column within it), so full <= partial"
        )
    return full, partial


def _tables(value) -> tuple[TableSpec, ...]:
    """`tables:`, the paper tables judged as a whole: [{table, label, group (optional)}]."""
    if not isinstance(value, list):
        raise Invalid(f"tables: expected a list of {{table, label, group}}, got {value!r}")
    out = []
    for i, t in enumerate(value):
        if not isinstance(t, dict) or not {"table", "label"} <= set(t):
            raise Invalid(f"tables[{i}]: needs table and label, got {t!r}")
        known(t, TABLE_KEYS, f"tables[{i}]: ", "a tables entry")
        out.append(TableSpec(str(t["table"]), str(t["label"]), t.get("group")))
    return tuple(out)


def check_manifests(claims: ClaimsFile) -> None:
    """Each manifest the claims file names is a file beside it: checked before any is read, so an unknown table is
    named with the claim (or entry) that names it, not found after the tables before it were built."""
    folder = claims.path.parent
    named = [(f"claims[{i}] ({c.id})", c.table) for i, c in enumerate(claims.claims)]
    named += [(f"tables[{i}]", t.table) for i, t in enumerate(claims.tables)]
    named += [(f"budget_study.{k}", str(claims.study[k])) for k in ("table", "floor_table") if claims.study.get(k)]
    for where, name in named:
        if not (folder / f"{name}.yaml").is_file():
            beside = ", ".join(p.stem for p in sorted(folder.glob("*.yaml")) if p.name != claims.path.name)
            raise ManifestError(
                f"{claims.path}: {where}: table {name!r} is no manifest (no {folder / name}.yaml); "
                f"the manifests beside it: {beside}"
            )


def _study(spec) -> dict:
    """`budget_study:` with each model's `compare` as a list of (alternative, cpu) pairs; one pair may be
    written bare ([a, b])."""
    if not isinstance(spec, dict):
        raise Invalid(f"budget_study: expected a mapping with table and compare, got {spec!r}")
    known(spec, STUDY_KEYS, "budget_study: ", "budget_study")
    if spec and "table" not in spec:
        raise Invalid("budget_study: needs table, the budget study's manifest")
    if not isinstance(spec.get("compare") or {}, dict):
        raise Invalid(f"budget_study.compare: expected {{model: [[a, b], ...]}}, got {spec['compare']!r}")
    spec = dict(spec)
    compare = {}
    for model, pairs in (spec.get("compare") or {}).items():
        pairs = [pairs] if pairs and all(isinstance(p, str) for p in pairs) else pairs
        if not pairs or not all(isinstance(p, list) and len(p) == 2 for p in pairs):
            raise Invalid(f"budget_study.compare.{model}: a pair [a, b] or a list of them")
        compare[str(model)] = [tuple(map(str, p)) for p in pairs]
    if compare:
        spec["compare"] = compare
    return spec
