"""A claims file (experiments/claims.yaml): the paper's claims, each a comparison of two manifest columns,
the tables judged as a whole and the budget study's notes, read and checked (meshseg/report/claims.py judges
them on the runs)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import yaml

from meshseg.errors import ManifestError

#: what a claim's `test` may be
TESTS = ("mean", "every_set", "most_sets", "equal", "refinement")
VERDICTS = ("reproduced", "contradicted", "inconclusive", "partly", "not yet run", "no data")


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
    try:
        doc = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(doc, dict) and "claims" in doc


def load_claims(path) -> ClaimsFile:
    """Read and check a claims file; every problem is reported with the file's name."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as e:
        raise ManifestError(f"{path}: cannot read the claims file: {e}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("claims"), list) or not doc["claims"]:
        raise ManifestError(f"{path}: a claims file is a mapping with a non-empty `claims:` list")
    claims, seen = [], set()
    for i, c in enumerate(doc["claims"]):
        where = f"claims[{i}]"
        if not isinstance(c, dict) or not {"id", "text", "table", "a"} <= set(c):
            raise ManifestError(f"{path}: {where}: needs id, text, table and a")
        test = c.get("test", "mean")
        if test not in TESTS:
            raise ManifestError(f"{path}: {where} ({c['id']}): test {test!r} is not one of {list(TESTS)}")
        if (test == "refinement") != (c.get("b") is None):
            raise ManifestError(f"{path}: {where} ({c['id']}): b is required, except with test: refinement")
        if str(c["id"]) in seen:
            raise ManifestError(f"{path}: {where}: id {c['id']!r} is used twice")
        seen.add(str(c["id"]))
        claims.append(
            Claim(
                str(c["id"]),
                " ".join(str(c["text"]).split()),
                str(c.get("source", "")),
                str(c["table"]),
                str(c["a"]),
                None if c.get("b") is None else str(c["b"]),
                test,
                None if c.get("sets") is None else tuple(str(s) for s in c["sets"]),
                c.get("group"),
                float(c.get("margin", 0.5)),
                float(c.get("min_share", 0.75)),
                tuple(str(m) for m in c.get("models", ())),
            )
        )
    tables = tuple(TableSpec(str(t["table"]), str(t["label"]), t.get("group")) for t in doc.get("tables") or [])
    thresholds = doc.get("thresholds") or {}
    return ClaimsFile(
        str(doc.get("name", path.stem)),
        str(doc.get("title", "Claims")),
        " ".join(str(doc.get("rule", "")).split()),
        tuple(doc.get("overrides") or ()),
        tuple(claims),
        tables,
        float(thresholds.get("full", 1.0)),
        float(thresholds.get("partial", 2.0)),
        _study(doc.get("budget_study") or {}, path),
        path,
    )


def _study(spec: dict, path: Path) -> dict:
    """`budget_study:` with each model's `compare` as a list of (alternative, cpu) pairs; one pair may be
    written bare ([a, b])."""
    spec = dict(spec)
    compare = {}
    for model, pairs in (spec.get("compare") or {}).items():
        pairs = [pairs] if pairs and all(isinstance(p, str) for p in pairs) else pairs
        if not pairs or not all(isinstance(p, list) and len(p) == 2 for p in pairs):
            raise ManifestError(f"{path}: budget_study.compare.{model}: a pair [a, b] or a list of them")
        compare[str(model)] = [tuple(map(str, p)) for p in pairs]
    if compare:
        spec["compare"] = compare
    return spec
