"""The claims report: verdicts by the rule experiments/claims.yaml states, on hand-made columns."""

import csv
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from meshseg.errors import ManifestError
from meshseg.report.aggregate import nested_stats
from meshseg.report.cells import Cell, Row, Table
from meshseg.report.claims import SetDiff, brief_table, build_report, decide, judge, summary_table
from meshseg.report.claims_file import Claim, ClaimsFile, TableSpec, load_claims
from meshseg.report.manifest import Column, Group, Manifest, Set, load_manifest

REPO = Path(__file__).resolve().parents[1]
A, B, P = Column("a", "A", ("x=1",)), Column("b", "B", ("x=2",)), Column("p", "P", None)


def table(sets: dict[str, tuple[list[float], list[float]]], missing: dict[str, int] | None = None) -> Table:
    """A manifest of columns a, b (runs) and p (published only) whose set s has per-mesh accuracies
    sets[s] = (a's, b's) on meshes m0, m1, ...; `missing` folds of column a per set (of 5)."""
    missing = missing or {}
    rows, meshes = [], []
    for name, (xa, xb) in sets.items():
        cells = []
        for col, xs, pub in ((A, xa, 95.0), (B, xb, 93.0)):
            gone = tuple(range(missing.get(name, 0))) if col is A else ()
            value = None if gone else float(np.mean(xs))
            cells.append(Cell(col, pub, value, n_meshes=0 if gone else len(xs), folds=5, missing=gone, budget="cpu"))
            # raw accuracies: a's stand in for refined - raw = a - b
            raws = np.array(xb, float) if col is A else np.array(xs, float)
            meshes += [(name, col.key, i, f"m{i}", float(x), r) for i, (x, r) in enumerate(zip(xs, raws))]
        cells.append(Cell(P, 94.0))
        rows.append(Row(name, "set", "G", tuple(cells)))
    groups = (Group("G", (), tuple(Set(s, s, (95.0, 93.0, 94.0)) for s in sets), None, (None, None, None)),)
    m = Manifest("t", "t", "", "", (), (A, B, P), groups, None, (None, None, None), Path("t.yaml"))
    # each mesh its own fold, one seed: leave-one-out, where the nested interval is the mesh bootstrap
    frame = pd.DataFrame(meshes, columns=["row", "column", "fold", "mesh", "acc", "acc_raw"]).assign(group="G")
    return Table(m, tuple(rows), (), "acc", 0.95, meshes=frame)


def claim(test="mean", **kw) -> Claim:
    return Claim("c", "a beats b", "§4", "t", "a", kw.pop("b", "b"), test, **kw)


RNG = np.random.default_rng(0)


@pytest.fixture(autouse=True)
def fresh_rng():
    """Each test draws the same numbers whatever ran before it (xdist changes the order)."""
    global RNG
    RNG = np.random.default_rng(0)


def noisy(center: float, n: int = 20) -> tuple[list[float], list[float]]:
    b = RNG.uniform(80, 95, n)
    return list(b + center + RNG.normal(0, 0.3, n)), list(b)


def test_a_consistent_positive_difference_is_reproduced_and_its_reverse_contradicted():
    t = table({"s1": noisy(1.0), "s2": noisy(1.5)})
    v = judge(claim(), t)
    assert v.verdict == "reproduced" and v.ci[0] > 0 and v.budget == "cpu" and v.published == pytest.approx(2.0)
    flipped = table({"s1": noisy(-1.0), "s2": noisy(-1.5)})
    assert judge(claim(), flipped).verdict == "contradicted"


def test_under_leave_one_out_with_one_seed_the_interval_is_the_mesh_bootstraps_to_the_last_digit():
    v = judge(claim("every_set"), table({"s1": noisy(1.0), "s2": noisy(-0.2)}))
    assert v.ci == v.ci_meshes and v.verdict == v.verdict_meshes and v.seeds == 1
    assert [s.ci for s in v.sets] == [s.ci_meshes for s in v.sets]


def reshaped(t: Table, folds: int, seeds: int = 1, shift: float = 0.0) -> Table:
    """`t` with its meshes dealt into `folds` folds (mesh i in fold i % folds) and each run made at `seeds`
    training seeds, seed k's accuracies of column a moved by k * shift."""
    m = t.meshes.assign(fold=[int(x[1:]) % folds for x in t.meshes["mesh"]])
    parts = [m.assign(seed=k, acc=m["acc"] + np.where(m["column"] == "a", k * shift, 0.0)) for k in range(seeds)]
    return Table(t.manifest, t.rows, (), "acc", 0.95, meshes=pd.concat(parts, ignore_index=True))


def width(ci) -> float:
    return ci[1] - ci[0]


def test_folds_that_differ_in_sign_widen_the_interval_beyond_the_mesh_bootstraps():
    """Five folds of four meshes, a - b +3 on three folds and -3 on two: resampling whole folds sees the
    folds' spread, which the mesh-level interval, treating the 20 meshes as independent, understates."""
    b = list(RNG.uniform(80, 95, 20))
    a = [x + (3.0 if i % 5 < 3 else -3.0) + RNG.normal(0, 0.1) for i, x in enumerate(b)]
    v = judge(claim(), reshaped(table({"s1": (a, b)}), folds=5))
    assert v.value == pytest.approx(0.6, abs=0.1)
    assert width(v.ci) > 1.5 * width(v.ci_meshes) and v.verdict == "inconclusive"


def test_seeds_that_agree_give_the_one_seed_interval_and_seeds_that_disagree_widen_it():
    t = table({"s1": noisy(1.0), "s2": noisy(0.8)})
    one = judge(claim(), reshaped(t, folds=5))
    agree = judge(claim(), reshaped(t, folds=5, seeds=2))
    assert agree.seeds == 2 and agree.ci == pytest.approx(one.ci) and agree.value == pytest.approx(one.value)
    apart = judge(claim(), reshaped(t, folds=5, seeds=2, shift=3.0))
    assert apart.value == pytest.approx(one.value + 1.5)  # the mean over seeds
    assert width(apart.ci) > 2 * width(one.ci)  # one seed's +3 or the other's: a draw of seeds moves it 1.5


def test_a_seed_run_in_one_fold_only_is_resampled_and_if_it_agrees_leaves_the_interval_as_it_is():
    """While the seed repeats run, a column has seed 1 in some folds only: its partial paired block (fold 0 at
    two seeds, the others at one) still gets replicates; a second seed equal to the first moves none, one 5 points
    up moves the mean by its share."""
    folds = [(RNG.uniform(80, 95, (1, 4)), RNG.uniform(80, 95, (1, 4))) for _ in range(5)]
    half = [(np.vstack([a, a]) if f == 0 else a, b) for f, (a, b) in enumerate(folds)]
    one = nested_stats(folds, 500, np.random.default_rng(1))
    assert nested_stats(half, 500, np.random.default_rng(1)) == pytest.approx(one)
    apart = [(np.vstack([a, a + 5.0]) if f == 0 else a, b) for f, (a, b) in enumerate(folds)]
    moved = nested_stats(apart, 500, np.random.default_rng(1)) - one  # fold 0: 4 of 20 meshes, +2.5 on average
    assert moved.mean() == pytest.approx(0.5, abs=0.15) and moved.std() > 0


def test_the_brief_table_says_how_many_seeds_each_verdict_rests_on():
    """The README's table: 2 where both columns ran at two seeds, — for a claim with a column not yet run."""
    cf = ClaimsFile("claims", "C", "rule", (), (claim(),), (), 1.0, 2.0, {}, Path("c.yaml"))
    t = table({"s1": noisy(1.0), "s2": noisy(0.8)})
    assert brief_table(build_report(cf, {"t": reshaped(t, folds=5, seeds=2)})).splitlines()[2].endswith(" | 2 |")
    pending = table({"s1": noisy(1.0), "s2": noisy(0.8)}, missing={"s1": 1})
    line = brief_table(build_report(cf, {"t": pending})).splitlines()[2]
    assert line.endswith("| not yet run (1 runs missing) | — |")


def test_differences_centred_on_zero_are_inconclusive():
    t = table({"s1": noisy(0.0, 40), "s2": noisy(0.0, 40)})
    v = judge(claim(), t)
    assert v.verdict == "inconclusive" and v.ci[0] < 0 < v.ci[1]


def test_one_set_against_an_every_set_claim_makes_it_partly_and_names_the_set():
    t = table({"s1": noisy(2.0), "s2": noisy(2.0), "s3": noisy(-1.0)})
    v = judge(claim("every_set"), t)
    assert v.verdict == "partly" and v.against == ["s3*"]  # * : s3's own interval excludes 0
    assert "against: s3*" in v.verdict_text
    assert judge(claim("every_set", sets=("s1", "s2")), t).verdict == "reproduced"  # the claim's own sets only


def test_a_missing_fold_is_not_yet_run_and_counted():
    t = table({"s1": noisy(1.0), "s2": noisy(1.0), "s3": noisy(1.0)}, missing={"s2": 2, "s3": 1})
    v = judge(claim(), t)
    assert v.verdict == "not yet run" and v.missing_runs == 3 and v.value is None
    assert v.verdict_text == "not yet run (3 runs missing)"


def test_the_paired_difference_by_hand():
    """Two sets: s1 meshes a - b = +1, +3 (mean 2); s2: -1, 0, +4 (mean 1). The claim's value is the mean of
    the set means, 1.5, not the mesh mean 1.4; each set's mean is its meshes' mean."""
    t = table({"s1": ([91.0, 93.0], [90.0, 90.0]), "s2": ([80.0, 85.0, 94.0], [81.0, 85.0, 90.0])})
    v = judge(claim(), t, n_boot=4000)
    assert [s.value for s in v.sets] == [pytest.approx(2.0), pytest.approx(1.0)]
    assert [s.n_meshes for s in v.sets] == [2, 3]
    assert v.value == pytest.approx(1.5)
    # resampling meshes within sets: s1's mean is 1, 2 or 3 and s2's lies in [-1, 4], so the interval lies in [0, 3.5]
    assert 0.0 <= v.ci[0] < 1.5 < v.ci[1] <= 3.5


def test_equal_against_a_published_only_column_and_refinement():
    t = table({"s1": ([94.2] * 10, [90.0] * 10), "s2": ([93.9] * 10, [90.0] * 10)})
    # a's mean 94.05 against P's published 94.0: +0.05, its interval inside +-0.5
    v = judge(claim("equal", b="p", margin=0.5), t)
    assert v.verdict == "reproduced" and v.value == pytest.approx(0.05) and v.published == pytest.approx(1.0)
    assert judge(claim("equal", b="b", margin=0.5), t).verdict == "contradicted"  # 4 points apart
    r = judge(claim("refinement", b=None), t)  # gains stand in as a - b here: +4.2, +3.9
    assert r.verdict == "reproduced" and r.value == pytest.approx(4.05) and r.published is None


def test_decide_most_sets_needs_its_share():
    sets = [SetDiff(f"s{i}", 1.0, (0.5, 1.5), 5) for i in range(4)] + [SetDiff("s4", -0.2, (-0.5, 0.1), 5)]
    assert decide("most_sets", (0.3, 1.2), sets, 0.5, 0.75) == ("reproduced", ["s4"])  # 4 of 5 >= 75 %
    assert decide("most_sets", (0.3, 1.2), sets, 0.5, 0.9) == ("partly", ["s4"])
    assert decide("every_set", (-0.1, 1.2), sets, 0.5, 0.75) == ("inconclusive", ["s4"])


def test_a_bad_claims_file_is_refused_with_its_name(tmp_path):
    bad = tmp_path / "claims.yaml"
    bad.write_text("claims:\n  - {id: '1', text: x, table: t, a: a, b: b, test: better}\n")
    with pytest.raises(ManifestError, match=r"claims.yaml: claims\[0\] \(1\): test 'better' is not one of"):
        load_claims(bad)
    bad.write_text("claims:\n  - {id: '1', text: x, table: t, a: a}\n")
    with pytest.raises(ManifestError, match=r"b is required, except with test: refinement"):
        load_claims(bad)
    one = "claims:\n  - {id: '1', text: x, table: t, a: a, b: b}\nbudget_study: {table: s, compare: {3B: %s}}\n"
    bad.write_text(one % "[x]")
    with pytest.raises(ManifestError, match=r"claims.yaml: budget_study.compare.3B: a pair \[a, b\] or a list"):
        load_claims(bad)
    bad.write_text(one % "[x, y]")  # one pair written bare, or a list of pairs
    assert load_claims(bad).study["compare"] == {"3B": [("x", "y")]}
    bad.write_text(one % "[[x, y], [z, y]]")
    assert load_claims(bad).tables_needed() == {"t": {"a", "b"}, "s": {"x", "y", "z"}}


def test_every_shipped_claim_names_columns_and_sets_its_manifest_has():
    claims = load_claims(REPO / "experiments/claims.yaml")
    assert {c.id for c in claims.claims} >= {"1", "2a", "3", "4", "5a", "6a", "7a", "8", "9", "10", "11", "12a"}
    for c in claims.claims:
        m = load_manifest(REPO / "experiments" / f"{c.table}.yaml")
        keys = {col.key for col in m.columns}
        assert c.a in keys and (c.b is None or c.b in keys), c
        group = next(g for g in m.groups if g.name == (c.group or m.groups[0].name))
        assert c.sets is None or set(c.sets) <= {s.name for s in group.sets}, c


def test_build_report_judges_tables_too():
    t = table({"s1": noisy(1.0), "s2": noisy(1.0)})
    cf = ClaimsFile("claims", "C", "rule", (), (claim(),), (TableSpec("t", "Table T"),), 1.0, 2.0, {}, Path("c.yaml"))
    report = build_report(cf, {"t": t})
    assert [v.verdict for v in report.verdicts] == ["reproduced"]
    assert report.tables[0].verdict == "not yet run"  # the hand-made table has no average row
    assert summary_table(report).splitlines()[2].startswith("| c | a beats b (§4) | +2.00 |")
    v = report.verdicts[0]
    assert brief_table(report).splitlines()[2] == f"| c | a > b (§4) | +2.00 | {v.reproduced_text} | reproduced | 1 |"
    for test, kw, text in (
        ("every_set", {"sets": ("s1",)}, "a > b on every set, s1 (§4)"),
        ("equal", {"margin": 0.5}, "a ≈ b (±0.5) (§4)"),
        ("refinement", {"b": None}, "a: refined > raw (§4)"),
    ):
        cf2 = ClaimsFile("claims", "C", "rule", (), (claim(test, **kw),), (), 1.0, 2.0, {}, Path("c.yaml"))
        assert brief_table(build_report(cf2, {"t": t})).splitlines()[2].startswith(f"| c | {text} |")


def test_the_readme_claims_table_matches_reports_claims_csv():
    """README "Does the paper reproduce?" is the claims report's table: same claims, numbers and verdicts."""
    readme = (REPO / "README.md").read_text()
    block = re.search(r"<!-- claims:begin -->\n(.*?)<!-- claims:end -->", readme, re.S)
    assert block, "README lacks the claims table between <!-- claims:begin --> and <!-- claims:end -->"
    claims_md = (REPO / "reports/claims/claims.md").read_text()
    assert block.group(1).strip() in claims_md  # the whole brief table (scripts/readme_claims.py)
    rows = [line.split(" | ") for line in block.group(1).splitlines() if re.match(r"\| \w+ \|", line)]
    shipped = list(csv.DictReader((REPO / "reports/claims/claims.csv").open()))
    assert [r[0].strip("| ") for r in rows] == [s["id"] for s in shipped]
    for r, s in zip(rows, shipped):
        assert r[4].split(" (")[0].split(";")[0] == s["verdict"], (r, s)
        assert r[5].rstrip(" |") == (s["seeds"] or "—"), (r, s)  # which verdicts rest on one seed
        if s["reproduced"]:
            assert r[3].startswith(f"{float(s['reproduced']):+.2f} ["), (r, s)
        else:
            assert r[3] == "—"


def test_the_budget_study_note_weighs_every_budget_alternative_and_names_those_that_move_it():
    t = table({"s1": noisy(1.0), "s2": noisy(1.0)})

    def effect(study, pairs=(("a", "b"),)):
        spec = {"table": "study", "compare": {"3B": list(pairs)}}
        c = Claim("c", "a beats b", "§4", "t", "a", "b", models=("3B",))
        cf = ClaimsFile("claims", "C", "rule", (), (c,), (), 1.0, 2.0, spec, Path("c.yaml"))
        return build_report(cf, {"t": t, "study": study}).verdicts[0]

    moved = effect(table({"s1": noisy(0.8), "s2": noisy(0.9)}))  # the alternative budget scores higher
    assert moved.budget_effect == "moves it (a)" and "3B a − b +0.8" in moved.notes[0]
    assert summary_table_line(moved).endswith("| cpu; budget study: moves it (a) |")
    assert effect(table({"s1": noisy(0.0, 40), "s2": noisy(0.0, 40)})).budget_effect == "no effect"
    pending = effect(table({"s1": noisy(1.0), "s2": noisy(1.0)}, missing={"s1": 1}))
    assert pending.budget_effect == "pending"
    assert "3B a − b: budget study not yet run (1 runs missing)" in pending.notes[0]
    # two alternatives, a (+0.8) and b against itself (0 exactly): only a moves it, and the note names it
    both = effect(table({"s1": noisy(0.8), "s2": noisy(0.9)}), pairs=(("a", "b"), ("b", "b")))
    assert both.budget_effect == "moves it (a)" and "3B b − b +0.00" in both.notes[0]


def test_a_claims_interval_is_the_study_reports_paired_interval_for_the_same_comparison():
    """The claims report and a study's paired block draw the same resamples for the same comparison, so
    the same a - b prints the same interval in both (budget study and claims once differed by 0.02)."""
    from dataclasses import replace

    from meshseg.report.aggregate import Bootstrap, compare

    t = table({"s1": noisy(0.3), "s2": noisy(0.1), "s3": noisy(-0.2)})
    avg = Row("Average", "average", "G", t.rows[0].cells)
    t = replace(t, rows=(*t.rows, avg))
    v, block = judge(claim(), t, n_boot=500, seed=3), compare(t, "a", "b", Bootstrap(500, 0.95, 3)).rows
    assert [s.ci for s in v.sets] == [r.ci for r in block[:3]]
    assert block[3].label == "Average" and v.ci == block[3].ci and v.value == pytest.approx(block[3].value)
    assert judge(claim(sets=("s1", "s2")), t, n_boot=500, seed=3).ci != v.ci  # part of the sets: its own


def summary_table_line(v) -> str:
    from meshseg.report.claims import ClaimsReport

    cf = ClaimsFile("claims", "C", "rule", (), (v.claim,), (), 1.0, 2.0, {}, Path("c.yaml"))
    return summary_table(ClaimsReport(cf, [v], [], [])).splitlines()[2]
