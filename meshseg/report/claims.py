"""Does the paper reproduce? Each claim of the paper (experiments/claims.yaml) judged on the logged runs.

A claim is a comparison of two manifest columns on the same test meshes: per set the mean per-mesh
difference a - b with a paired bootstrap interval, over the claim's sets the mean of those (each set
weighs the same, its meshes resampled on their own), and a verdict by the rule the claims file states:

- reproduced: the claimed direction, its interval excludes 0 (for `equal`: inside +-margin);
- contradicted: the opposite direction, its interval excludes 0 (for `equal`: wholly outside +-margin);
- inconclusive: the interval holds 0;
- partly: an `every_set` (or `most_sets`) claim whose mean holds but some sets go against it, named;
- not yet run: a cell lacks runs (the count says how many); no data: the data are not at hand here.

Each paper table also gets a verdict of the AEA data editor's kind (full / partial / not reproduced)
from its columns' averages against the published ones and its claims' verdicts, with the thresholds the
claims file writes down.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from meshseg.errors import ManifestError
from meshseg.report.aggregate import Bootstrap, accuracies, gains, nested_units, paired_differences
from meshseg.report.cells import Cell, Table
from meshseg.report.claims_file import Claim, ClaimsFile, TableSpec, load_claims


@dataclass
class SetDiff:
    name: str
    value: float | None  # mean a - b over its test meshes, points
    ci: tuple[float, float] | None  # resampling seeds, folds, then meshes (aggregate.nested_interval)
    n_meshes: int
    ci_meshes: tuple[float, float] | None = None  # resampling the test meshes alone


@dataclass
class Verdict:
    claim: Claim
    verdict: str
    value: float | None = None  # the mean over the claim's sets of a - b, points
    ci: tuple[float, float] | None = None
    published: float | None = None  # the same difference in the paper's numbers
    sets: list[SetDiff] = field(default_factory=list)
    against: list[str] = field(default_factory=list)  # sets that go against the claim (* : interval excludes 0)
    missing_runs: int = 0
    budget: str = ""  # the budget(s) of the evidence
    notes: list[str] = field(default_factory=list)
    budget_effect: str = ""  # the budget study's word: pending | moves it (which) | no effect ("": not asked)
    #: the verdict the interval over test meshes alone gives (the rule before 2026-12-02), for comparison,
    #: and how many training seeds the evidence has (the fewest of its columns)
    ci_meshes: tuple[float, float] | None = None
    verdict_meshes: str = ""
    seeds: int = 0

    @property
    def reproduced_text(self) -> str:
        if self.value is None:
            return "—"
        return f"{self.value:+.2f} [{self.ci[0]:+.2f}, {self.ci[1]:+.2f}]"

    @property
    def meshes_text(self) -> str:
        """The interval over test meshes alone, and the verdict it gives where that is another."""
        if self.ci_meshes is None:
            return "—"
        other = "" if self.verdict_meshes == self.verdict else f": {self.verdict_meshes}"
        return f"[{self.ci_meshes[0]:+.2f}, {self.ci_meshes[1]:+.2f}]{other}"

    @property
    def verdict_text(self) -> str:
        text = self.verdict
        if self.verdict == "not yet run":
            text += f" ({self.missing_runs} runs missing)"
        if self.against and self.verdict in ("partly", "inconclusive", "reproduced"):
            text += f"; against: {', '.join(self.against)}"
        return text


def _rows(table: Table, claim: Claim):
    """The set rows of the claim's group and sets, and the column indexes of a and b."""
    keys = [c.key for c in table.columns]
    for k in (claim.a, claim.b):
        if k is not None and k not in keys:
            raise ManifestError(f"{table.manifest.path}: claim {claim.id}: no column {k!r}; its columns are {keys}")
    group = claim.group or table.manifest.groups[0].name
    rows = [r for r in table.rows if r.kind == "set" and r.group == group]
    if claim.sets is not None:
        unknown = set(claim.sets) - {r.label for r in rows}
        if unknown:
            where = f"{table.manifest.path}: claim {claim.id}"
            raise ManifestError(f"{where}: no set(s) {sorted(unknown)} in group {group}")
        rows = [r for r in rows if r.label in claim.sets]
    ia, ib = keys.index(claim.a), None if claim.b is None else keys.index(claim.b)
    # a set outside a column's `sets:` (a budget-study column run on some sets only) is no part of the claim
    rows = [r for r in rows if all(r.cells[j].status != "n/a" for j in (ia, ib) if j is not None)]
    return rows, ia, ib


def _budget(cells: list[Cell]) -> str:
    return ", ".join(sorted({c.budget for c in cells if c.budget and c.column.predictions is None}))


def _group_average(table: Table, group: str):
    """The group's own average row (not an also_average row over part of it), or None."""
    return next((r for r in table.rows if r.kind == "average" and r.group == group and not r.sets), None)


def _published_difference(table: Table, claim: Claim, rows, ia: int, ib: int | None) -> float | None:
    """The claim's difference in the paper's numbers: the group's published averages when the claim takes
    every set of the group, else the mean over its sets of the published set differences."""
    if ib is None:
        return None
    group = claim.group or table.manifest.groups[0].name
    if claim.sets is None:
        avg = _group_average(table, group)
        if avg is not None:
            pa, pb = avg.cells[ia].published, avg.cells[ib].published
            return None if pa is None or pb is None else pa - pb
    pubs = [(r.cells[ia].published, r.cells[ib].published) for r in rows]
    if any(pa is None or pb is None for pa, pb in pubs):
        return None
    return float(np.mean([pa - pb for pa, pb in pubs]))


def _identity(table: Table, claim: Claim, row) -> tuple[str, ...]:
    """The bootstrap identity of a claim's interval on set `row` (None: over the claim's sets): the one the
    study report's paired (or refinement) block gives the same comparison, so both print the same interval;
    a claim on part of a group's sets, or against a published-only column, has its own."""
    group = claim.group or table.manifest.groups[0].name
    if row is None:
        if claim.sets is not None:
            return ("claim", claim.id)
        row = _group_average(table, group)
        if row is None:
            return ("claim", claim.id)
    if claim.test == "refinement":
        return ("refinement", row.kind, row.group, row.label, claim.a)
    if next(c for c in table.columns if c.key == claim.b).overrides is None:  # against the paper's number
        return ("claim", claim.id, *((row.label,) if row.kind == "set" else ()))
    return ("paired", row.kind, row.group, row.label, claim.a, claim.b)


def _units(table: Table, rows, claim: Claim, ib: int | None) -> list[list]:
    """Per set row, the claim's folds for the nested interval (aggregate.nested_units)."""
    out = []
    for r in rows:
        if claim.test == "refinement":
            out.append(nested_units(table.meshes, r, claim.a, None, "gain"))
            continue
        cb = r.cells[ib]
        if cb.column.overrides is None:  # published only: a's accuracy against the paper's number
            out.append(nested_units(table.meshes, r, claim.a, None, table.metric, cb.published))
            continue
        out.append(nested_units(table.meshes, r, claim.a, claim.b, table.metric))
    return out


def _differences(table: Table, rows, claim: Claim, ib: int | None) -> list[np.ndarray]:
    """Per set row, the per-mesh differences the claim is judged on (every cell complete)."""
    out = []
    for r in rows:
        if claim.test == "refinement":
            out.append(gains(table.meshes, r, claim.a))
            continue
        cb = r.cells[ib]
        if cb.column.overrides is None:  # published only: a's accuracy against the paper's number
            out.append(accuracies(table.meshes, r, claim.a, table.metric) - cb.published)
            continue
        out.append(paired_differences(table.meshes, r, claim.a, claim.b, table.metric))
    return out


def decide(test: str, ci: tuple[float, float], sets: list[SetDiff], margin: float, min_share: float):
    """(verdict, the sets against the claim) from the mean's interval and the per-set differences."""
    lo, hi = ci
    if test == "equal":
        if -margin <= lo and hi <= margin:
            return "reproduced", []
        return ("contradicted" if hi < -margin or lo > margin else "inconclusive"), []
    base = "reproduced" if lo > 0 else "contradicted" if hi < 0 else "inconclusive"
    if test in ("mean", "refinement"):
        return base, []
    against = [s.name + ("*" if s.ci[1] < 0 else "") for s in sets if s.value <= 0]
    if base != "reproduced" or not against:
        return base, against
    share = 1 - len(against) / len(sets)
    if test == "most_sets" and share >= min_share:
        return "reproduced", against
    return "partly", against


def judge(claim: Claim, table: Table, n_boot: int = 2000, seed: int = 0) -> Verdict:
    """The claim's verdict from the table of its manifest (pure: no store, no files)."""
    rows, ia, ib = _rows(table, claim)
    cols = [ia] if ib is None else [ia, ib]
    cells = [r.cells[j] for r in rows for j in cols if r.cells[j].column.overrides is not None]
    v = Verdict(claim, "no data", budget=_budget(cells))
    v.published = _published_difference(table, claim, rows, ia, ib)
    if not rows or any(c.status == "unavailable" for c in cells):
        return v
    if any(c.status == "incomplete" for c in cells):
        v.verdict, v.missing_runs = "not yet run", sum(c.runs_missing for c in cells if c.status == "incomplete")
        return v
    if claim.test == "refinement" and any(gains(table.meshes, r, claim.a) is None for r in rows):
        v.verdict = "no data"
        v.notes.append("no raw accuracies logged")
        return v
    boot = Bootstrap(n_boot, table.level, seed)
    diffs, units = _differences(table, rows, claim, ib), _units(table, rows, claim, ib)
    for r, d, u in zip(rows, diffs, units):
        ident = _identity(table, claim, r)
        v.sets.append(SetDiff(r.label, float(d.mean()), boot.nested([u], *ident), len(d), boot.interval([d], *ident)))
    v.value = float(np.mean([d.mean() for d in diffs]))
    v.ci = boot.nested(units, *_identity(table, claim, None))
    v.verdict, v.against = decide(claim.test, v.ci, v.sets, claim.margin, claim.min_share)
    v.ci_meshes = boot.interval(diffs, *_identity(table, claim, None))
    mesh_sets = [SetDiff(s.name, s.value, s.ci_meshes, s.n_meshes) for s in v.sets]
    v.verdict_meshes = decide(claim.test, v.ci_meshes, mesh_sets, claim.margin, claim.min_share)[0]
    v.seeds = min(x.shape[0] for u in units for pair in u for x in pair if x is not None)
    return v


@dataclass
class TableVerdict:
    spec: TableSpec
    verdict: str  # full | partial | not reproduced | not yet run | no data
    columns: list[tuple[str, float | None, float | None]]  # (label, reproduced average, published average)
    why: str


def judge_table(spec: TableSpec, table: Table, verdicts: list[Verdict], full: float, partial: float) -> TableVerdict:
    """full: every run column complete and within `full` points of its published average, no claim on the
    table contradicted; partial: some run column complete and within `partial`; not reproduced: complete
    columns, none within `partial`; not yet run: no run column complete; no data: no run can be made here."""
    group = spec.group or table.manifest.groups[0].name
    avg = _group_average(table, group)
    runs = [j for j, c in enumerate(table.columns) if c.overrides is not None and c.predictions is None]
    cells = [avg.cells[j] for j in runs] if avg is not None else []
    cols = [(c.column.label, c.value, c.published) for c in cells]
    done = [(lab, x, p) for lab, x, p in cols if x is not None and p is not None]
    mine = [v for v in verdicts if v.claim.table == spec.table and (v.claim.group or group) == group]
    against = [v.claim.id for v in mine if v.verdict == "contradicted"]
    if cells and all(c.status == "unavailable" for c in cells):
        return TableVerdict(spec, "no data", cols, "the data are not at hand here")
    if not done:
        return TableVerdict(spec, "not yet run", cols, f"0 of {len(cells)} run columns complete")
    gaps = {lab: x - p for lab, x, p in done}
    within = [lab for lab, g in gaps.items() if abs(g) <= partial]
    text = f"{len(done)} of {len(cells)} run columns complete; " + ", ".join(f"{k} {g:+.2f}" for k, g in gaps.items())
    if against:
        text += f"; claims contradicted: {', '.join(against)}"
    if len(done) == len(cells) and all(abs(g) <= full for g in gaps.values()) and not against:
        return TableVerdict(spec, "full", cols, text)
    return TableVerdict(spec, "partial" if within else "not reproduced", cols, text)


def budget_note(claim: Claim, study: Table | None, spec: dict, n_boot: int, seed: int) -> tuple[str, str]:
    """What the budget study says of the models the claim's evidence rests on: per model and per budget
    alternative the study ran, the alternative minus `cpu` over its sets, and whether that moves results
    (interval excludes 0). Returns (the note, its gist: pending | moves it (the alternatives that do) | no
    effect; both empty where the claim names no model)."""
    if not claim.models or study is None:
        return "", ""
    parts, movers, pending = [], [], False
    for model in claim.models:
        for a, b in spec["compare"][model]:
            v = judge(Claim(f"budget {model}", "", "", study.manifest.name, a, b), study, n_boot, seed)
            if v.value is None:
                parts.append(f"{model} {a} − {b}: budget study {v.verdict_text}")
                pending = True
                continue
            moves = v.ci[0] > 0 or v.ci[1] < 0
            movers += [a] if moves else []
            parts.append(f"{model} {a} − {b} {v.reproduced_text}: {'moves it' if moves else 'does not move it'}")
    effect = f"moves it ({', '.join(movers)})" if movers else "pending" if pending else "no effect"
    return "; ".join(parts), effect


@dataclass
class FloorRow:
    column: str
    set: str
    delta: float | None  # reproduced - published
    floor: float | None  # how far the fold lists alone move this set (measured, or the largest measured)
    measured: bool  # the floor is this set's own


def noise_floor(study: Table, spec: dict, target: Table) -> list[FloorRow]:
    """Each set's distance from the published number beside how far another fold dealing moves it: the
    floor of a set is |acc(other dealing) - acc(meshseg's dealing)| of the same model, measured in the budget
    study; a set the study did not deal again takes the largest floor measured."""
    rows = []
    for model, (a, b) in spec.get("fold_lists", {}).items():
        keys = [c.key for c in study.columns]
        ia, ib = keys.index(a), keys.index(b)
        floors = {
            r.label: abs(r.cells[ia].value - r.cells[ib].value)
            for r in study.rows
            if r.kind == "set" and r.cells[ia].value is not None and r.cells[ib].value is not None
        }
        col = spec["floor_columns"][model]
        j = [c.key for c in target.columns].index(col)
        for r in (r for r in target.rows if r.kind == "set"):
            cell = r.cells[j]
            mine = floors.get(r.label)
            floor = mine if mine is not None else max(floors.values()) if floors else None
            rows.append(FloorRow(target.columns[j].label, r.label, cell.delta, floor, mine is not None))
    return rows


@dataclass
class ClaimsReport:
    claims: ClaimsFile
    verdicts: list[Verdict]
    tables: list[TableVerdict]
    floors: list[FloorRow]


def build_report(claims: ClaimsFile, tables: dict[str, Table], n_boot: int = 2000, seed: int = 0) -> ClaimsReport:
    """Every claim and table judged on `tables` ({manifest name: its table}; the budget study's too)."""
    study = tables.get(claims.study.get("table")) if claims.study else None
    verdicts = []
    for c in claims.claims:
        v = judge(c, tables[c.table], n_boot, seed)
        note, v.budget_effect = budget_note(c, study, claims.study, n_boot, seed)
        if note:
            v.notes.append(note)
        verdicts.append(v)
    judged = [judge_table(t, tables[t.table], verdicts, claims.full, claims.partial) for t in claims.tables]
    floors = []
    if study is not None and claims.study.get("floor_table") in tables:
        floors = noise_floor(study, claims.study, tables[claims.study["floor_table"]])
    return ClaimsReport(claims, verdicts, judged, floors)


def _num(x: float | None, signed: bool = True) -> str:
    return "—" if x is None else f"{x:+.2f}" if signed else f"{x:.2f}"


def summary_table(report: ClaimsReport) -> str:
    """The one-line-per-claim Markdown table in the paper's words, with the interval over meshes alone, the seeds
    and the budget (claims.md)."""
    lines = [
        "| # | claim (paper) | published | reproduced [95 % CI] | verdict | seeds | meshes alone | budget |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for v in report.verdicts:
        c = v.claim
        budget = (v.budget or "—") + (f"; budget study: {v.budget_effect}" if v.budget_effect else "")
        lines.append(
            f"| {c.id} | {c.text} ({c.source}) | {_num(v.published)} | {v.reproduced_text} | "
            f"{v.verdict_text} | {v.seeds or '—'} | {v.meshes_text} | {budget} |"
        )
    return "\n".join(lines)


def _brief(claim: Claim) -> str:
    """A claim as its comparison, e.g. "3B > 1B (§4, Table 2)"; the paper's words are in the full table."""
    a, b = claim.a, claim.b
    text = {
        "refinement": f"{a}: refined > raw",
        "equal": f"{a} ≈ {b} (±{claim.margin:g})",
        "every_set": f"{a} > {b} on every set",
        "most_sets": f"{a} > {b} in most sets",
    }.get(claim.test, f"{a} > {b}")
    sets = f", {'/'.join(claim.sets)}" if claim.sets else ""
    return f"{text}{sets} ({claim.source})"


def brief_table(report: ClaimsReport) -> str:
    """The claims table in brief (the README's "Does the paper reproduce?"): each claim as its comparison, and how
    many training seeds its verdict rests on (the fewest of its columns; — where nothing ran)."""
    lines = ["| # | claim (a > b) | published | reproduced [95 % CI] | verdict | seeds |", "|---|---|---|---|---|---|"]
    for v in report.verdicts:
        lines.append(
            f"| {v.claim.id} | {_brief(v.claim)} | {_num(v.published)} | {v.reproduced_text} | {v.verdict_text} | "
            f"{v.seeds or '—'} |"
        )
    return "\n".join(lines)


def markdown(report: ClaimsReport) -> str:
    c = report.claims
    out = [f"# {c.title}", "", f"Rule ({c.path.name}): {c.rule}", "", brief_table(report), ""]
    out += ["## In the paper's words", "", summary_table(report), ""]
    out += ["## Per table", "", "| table | verdict | why |", "|---|---|---|"]
    out += [f"| {t.spec.label} | {t.verdict} | {t.why} |" for t in report.tables]
    out += ["", f"Thresholds: full within {c.full:.1f} points, partial within {c.partial:.1f} (column averages).", ""]
    out += ["## Per claim, per set", ""]
    for v in report.verdicts:
        out.append(
            f"**{v.claim.id}** ({v.claim.table}: {v.claim.a}{' − ' + v.claim.b if v.claim.b else ''}, "
            f"test {v.claim.test}): {v.verdict_text}"
            + (f"; {v.seeds} seed(s); over test meshes alone {v.meshes_text}" if v.ci_meshes else "")
            + "".join(f". {n}" for n in v.notes)
        )
        if v.sets:
            out.append("")
            out.append(" · ".join(f"{s.name} {s.value:+.2f} [{s.ci[0]:+.2f}, {s.ci[1]:+.2f}]" for s in v.sets))
        out.append("")
    if report.floors and all(f.floor is None for f in report.floors):
        out += ["## Distance from the published numbers against the fold-list noise floor", ""]
        out += ["Not measured yet: the budget study's other fold dealing (split.seed=1) has no complete set.", ""]
    elif report.floors:
        out += ["## Distance from the published numbers against the fold-list noise floor", ""]
        out += ["| column | set | reproduced − published | fold-list floor | beyond it |", "|---|---|---|---|---|"]
        for f in report.floors:
            beyond = "—" if f.delta is None or f.floor is None else "yes" if abs(f.delta) > f.floor else "no"
            own = "" if f.measured else " (largest measured)"
            out.append(f"| {f.column} | {f.set} | {_num(f.delta)} | {_num(f.floor, False)}{own} | {beyond} |")
        out.append("")
    return "\n".join(out)


def csv_text(report: ClaimsReport) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["id", "claim", "source", "table", "a", "b", "test", "published", "reproduced", "ci_low", "ci_high",
                "verdict", "against", "missing_runs", "budget", "budget_effect", "notes",
                "meshes_ci_low", "meshes_ci_high", "verdict_meshes", "seeds"])  # fmt: skip
    for v in report.verdicts:
        c = v.claim
        w.writerow([
            c.id, c.text, c.source, c.table, c.a, c.b or "", c.test,
            "" if v.published is None else f"{v.published:.4f}",
            "" if v.value is None else f"{v.value:.4f}",
            "" if v.ci is None else f"{v.ci[0]:.4f}", "" if v.ci is None else f"{v.ci[1]:.4f}",
            v.verdict, ";".join(v.against), v.missing_runs, v.budget, v.budget_effect, " ".join(v.notes),
            "" if v.ci_meshes is None else f"{v.ci_meshes[0]:.4f}",
            "" if v.ci_meshes is None else f"{v.ci_meshes[1]:.4f}", v.verdict_meshes, v.seeds or "",
        ])  # fmt: skip
    return buf.getvalue()


def figure(report: ClaimsReport):
    """One row per claim: the paired difference with its interval, the published difference as a mark."""
    from matplotlib.figure import Figure

    vs = report.verdicts
    fig = Figure(figsize=(8, 0.32 * len(vs) + 1.2), layout="constrained")
    ax = fig.subplots()
    colors = {"reproduced": "C2", "contradicted": "C3", "inconclusive": "C7", "partly": "C1"}
    for i, v in enumerate(vs):
        y = len(vs) - 1 - i
        if v.value is not None:
            ax.errorbar(v.value, y, xerr=[[v.value - v.ci[0]], [v.ci[1] - v.value]], fmt="o", ms=4, capsize=2,
                        color=colors.get(v.verdict, "k"))  # fmt: skip
        else:
            ax.text(-0.05, y, v.verdict, fontsize=6, va="center", ha="right", color="0.4")
        if v.published is not None:
            ax.plot(v.published, y, "kx", ms=5)
    ax.axvline(0, color="k", lw=0.6)
    ax.set_yticks(range(len(vs)), [f"{v.claim.id}: {v.claim.a} − {v.claim.b or 'raw'}" for v in reversed(vs)],
                  fontsize=6)  # fmt: skip
    ax.set_xlabel("difference a − b (points); dot: reproduced with 95 % interval, x: published")
    ax.set_title(report.claims.title, fontsize=9)
    return fig


def write(report: ClaimsReport, out_dir) -> list[Path]:
    """claims.md, claims.csv and claims.png under out_dir, each written whole or not at all."""
    from meshseg.report.write import png_bytes, write_files

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    contents = {"claims.md": markdown(report), "claims.csv": csv_text(report), "claims.png": png_bytes(figure(report))}
    return write_files(out, contents)


def collect_tables(claims: ClaimsFile, cfg) -> dict[str, Table]:
    """The tables the claims read, from the runs' store (shipped results/ imported first, as every report
    does): each manifest once, with the columns its claims, its table verdicts and the budget notes need."""
    from meshseg.report.config import run_overrides
    from meshseg.report.manifest import load_manifest
    from meshseg.report.publish import bootstrap, import_results
    from meshseg.report.runs import one_search_per_store
    from meshseg.report.table import collect

    s = cfg.report
    overrides = [*claims.overrides, *run_overrides(cfg)]
    judged = {t.table for t in claims.tables}
    manifests = {}
    for name, keys in claims.tables_needed().items():
        manifest = load_manifest(claims.path.parent / f"{name}.yaml")
        if name in judged:  # its verdict reads every run column's average
            keys = keys | {c.key for c in manifest.columns if c.overrides is not None}
        manifests[name] = manifest.only_columns([c.key for c in manifest.columns if c.key in keys])
    import_results(list(manifests.values()), cfg, overrides=overrides)  # the runs the tables below read
    with one_search_per_store():  # every import is done: the stores no longer change under the tables
        return {
            name: collect(manifest, overrides, metric=s.metric, paired=[], boot=bootstrap(s))  # claims pair themselves
            for name, manifest in manifests.items()
        }


def claims_from_config(cfg) -> tuple[ClaimsReport, list[Path]]:
    """`python -m meshseg.report experiments/claims.yaml`: every claim judged, written under
    <report.out_dir>/<claims name>/."""
    claims = load_claims(cfg.manifest)
    report = build_report(claims, collect_tables(claims, cfg), int(cfg.report.n_boot), int(cfg.report.seed))
    return report, write(report, Path(cfg.report.out_dir) / claims.name)
