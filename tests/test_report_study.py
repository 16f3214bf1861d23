"""A study manifest's keys (experiments/budget_study.yaml): a column's `sets:` (its other cells n/a: a dash,
not counted, never launched), the manifest's `paired:` blocks (report.paired replaces them) and `curves:` (the
learning-curve figure, placed by the runs' logged counts). On a hand-made two-mesh L-PSB folder: labellings
scored from disk and fold runs logged by hand, so every number is computed by hand."""

import csv
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO, tiny_manifest, tiny_psb
from omegaconf import OmegaConf

from meshseg.errors import ManifestError
from meshseg.report import collect, load_manifest, report
from meshseg.report.aggregate import Bootstrap
from meshseg.report.cells import progress
from meshseg.report.curves import curve_panels
from meshseg.report.write import write_report
from meshseg.reproduce import MissingCell, missing_cells, reproduce
from meshseg.tracking import Tracker


@pytest.fixture
def tiny(tmp_path, monkeypatch):
    """An L-PSB-shaped folder (category Tiny, meshes 1 and 2), labellings of them scoring 80 and 66.67 (pred)
    and 100 and 66.67 (pred2), and run overrides that point the runs' store into tmp_path."""
    tiny_psb(tmp_path)
    for name, one, two in (
        ("pred", "body\n1 2\n", "head\n1\nbody\n2 3\n"),
        ("pred2", "head\n1\nbody\n2\n", "head\n1 2 3\n"),
    ):
        (tmp_path / name).mkdir()
        (tmp_path / name / "1.lab").write_text(one)
        (tmp_path / name / "2.lab").write_text(two)
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path


def run_args(tiny) -> list[str]:
    return [f"paths.mlflow_dir={tiny / 'mlruns'}"]


def study(tiny, columns, **keys) -> Path:
    """Manifest `study`: sets One and Two, both the category Tiny (published 90 and 91 in every column)."""
    n = len(columns)
    sets = [{"name": "One", "category": "Tiny", "published": [90.0] * n}]
    sets.append({"name": "Two", "category": "Tiny", "published": [91.0] * n})
    return tiny_manifest(tiny, "study", columns, sets, 90.5, **keys)


def labellings(tiny, key: str, folder: str, **more) -> dict:
    return {"key": key, "label": key, "predictions": {"path": str(tiny / folder), "format": "psb_labels"}, **more}


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def line(md: str, start: str) -> str:
    return next(x for x in md.splitlines() if x.startswith(start))


# --- sets: -----------------------------------------------------------------------------------------------


def test_a_column_restricted_to_some_sets_is_na_elsewhere_and_never_launched(tiny):
    cols = [labellings(tiny, "K", "pred"), {"key": "R", "label": "R", "overrides": ["model=cnn1d"], "sets": ["Two"]}]
    path = study(tiny, cols)
    table = collect(load_manifest(path), run_args(tiny), boot=Bootstrap(50))
    status = {(r.label, c.column.key): c.status for r in table.rows for c in r.cells}
    assert status == {
        ("One", "K"): "ok",
        ("One", "R"): "n/a",
        ("Two", "K"): "ok",
        ("Two", "R"): "incomplete",  # an empty store: both leave-one-out folds missing
        ("Average", "K"): "ok",
        ("Average", "R"): "n/a",  # R covers part of the group: no average
    }
    p = progress(table)
    assert (p.cells, p.cells_done, p.runs_missing, p.unavailable) == (1, 0, 2, 0)  # the n/a cell is not counted
    (m,) = missing_cells(table)
    assert m == MissingCell("Two", "R", m.overrides, "Tiny", (0, 1))
    dry = reproduce(path, [*run_args(tiny), "report.dry_run=true", "report.results=null"])
    assert [(c.row, c.column, c.folds) for c in dry.launched] == [("Two", "R", (0, 1))]

    out = tiny / "out"
    write_report(table, out)
    md = (out / "table.md").read_text()
    assert line(md, "| One |").endswith("| — |") and line(md, "| **Average** |").endswith("| — |")
    assert line(md, "| Two |").endswith("| — (0/2) / 91.00 |")
    assert "0 of 1 cells complete; 2 fold runs missing." in md
    tex, html = (out / "table.tex").read_text(), (out / "table.html").read_text()
    assert line(tex, "One &").endswith(r"& — & -- & -- \\")
    assert "<td>—</td><td>—</td><td>—</td></tr>" in html
    (one,) = [r for r in read_csv(out / "table.csv") if (r["row"], r["column"]) == ("One", "R")]
    assert (one["status"], one["reproduced"], one["published"], one["delta"]) == ("n/a", "", "", "")
    assert one["why"] == "R is run on Two only"


def test_a_columns_sets_name_sets_of_the_manifest(tiny):
    cols = [labellings(tiny, "K", "pred", sets=["Two", "Three", "Four"])]
    with pytest.raises(
        ManifestError, match=r"column K: sets \['Three', 'Four'\] name no set of the manifest; its sets: One, Two$"
    ):
        load_manifest(study(tiny, cols))
    # a set may be named by its category, as report.sets takes it: Table 2's FourLeg is the set Fourleg
    budget = {c.key: c.sets for c in load_manifest(REPO / "experiments/budget_study.yaml").columns}
    assert budget["1B_s1"] == ("Vase", "Cup", "Hand", "Fourleg") and budget["1B_4k"] == ("Vase", "Hand")
    assert budget["1B"] is None


@pytest.mark.parametrize(
    "keys, problem",
    [
        ({"paired": [["A", "X"]]}, r"paired \['A', 'X'\]: \['X'\] name no column; the columns are A, B$"),
        ({"paired": [["A", "B", "A"]]}, r"paired: \[\['A', 'B', 'A'\]\] are not pairs"),
        ({"paired": "A"}, "paired: expected a list of"),
        ({"curves": {"x": "epochs", "series": {"s": ["A"]}}}, "curves: expected"),
        ({"curves": {"x": "samples", "series": {"s": ["A", "Z"]}}}, r"curves series s: \['Z'\] name no column"),
    ],
)
def test_bad_pairs_and_curves_are_refused(tiny, keys, problem):
    cols = [labellings(tiny, "A", "pred2"), labellings(tiny, "B", "pred")]
    with pytest.raises(ManifestError, match=problem):
        load_manifest(study(tiny, cols, **keys))


# --- paired: ---------------------------------------------------------------------------------------------


def pair_rows(path: Path) -> list[tuple]:
    return [(r["row"], r["a"], r["b"], r["delta"], r["n_meshes"]) for r in read_csv(path)]


def test_the_manifests_pairs_make_one_block_each_and_report_paired_replaces_them(tiny):
    """A scores 100 and 66.67 on meshes 1 and 2, B 80 and 66.67: A - B is 20 and 0 mesh by mesh, 10 on
    each set. C is A on set One only: C - B is compared on One, and its average says so."""
    cols = [labellings(tiny, "A", "pred2"), labellings(tiny, "B", "pred"), labellings(tiny, "C", "pred2", sets=["One"])]
    path = study(tiny, cols, paired=[["A", "B"], ["C", "B"]])
    args = [*run_args(tiny), "report.log=false", "report.n_boot=400", "report.results=null"]
    table, files, _ = report(path, [*args, f"report.out_dir={tiny / 'out'}"])
    assert [(p.a.key, p.b.key) for p in table.pairs] == [("A", "B"), ("C", "B")]
    ab, cb = table.pairs
    assert [(r.label, r.value, r.n_meshes) for r in ab.rows] == [
        ("One", 10.0, 2),
        ("Two", 10.0, 2),
        ("Average", 10.0, 4),
    ]
    assert [(r.label, r.value, r.n_meshes) for r in cb.rows] == [("One", 10.0, 2), ("Average (1 of 2 sets)", 10.0, 2)]
    assert ab.rows[0].ci == pytest.approx((0.0, 20.0)) and cb.rows[1].ci == pytest.approx((0.0, 20.0))  # {20, 0}
    md = (tiny / "out/study/table.md").read_text()
    assert "**Paired comparison: A − B**" in md and "**Paired comparison: C − B**" in md
    assert "| **Average (1 of 2 sets)** | +10.00 [+0.00, +20.00] | 2 |" in md
    assert pair_rows(tiny / "out/study/paired.csv") == [
        ("One", "A", "B", "10.0000", "2"),
        ("Two", "A", "B", "10.0000", "2"),
        ("Average", "A", "B", "10.0000", "4"),
        ("One", "C", "B", "10.0000", "2"),
        ("Average (1 of 2 sets)", "C", "B", "10.0000", "2"),
    ]

    table, _, _ = report(path, [*args, "report.paired=[B,A]", f"report.out_dir={tiny / 'given'}"])
    assert [(p.a.key, p.b.key) for p in table.pairs] == [("B", "A")]
    assert pair_rows(tiny / "given/study/paired.csv") == [
        ("One", "B", "A", "-10.0000", "2"),
        ("Two", "B", "A", "-10.0000", "2"),
        ("Average", "B", "A", "-10.0000", "4"),
    ]
    table, _, _ = report(path, [*args, "report.paired=[[C,B],[A,B]]", f"report.out_dir={tiny / 'two'}"])
    assert [(p.a.key, p.b.key) for p in table.pairs] == [("C", "B"), ("A", "B")]
    table, files, _ = report(path, [*args, "report.paired=[]", f"report.out_dir={tiny / 'none'}"])
    assert table.pairs == () and not (tiny / "none/study/paired.csv").exists()
    report(path, [*args, "report.paired=[]", f"report.out_dir={tiny / 'out'}"])  # over a report that had them
    assert not (tiny / "out/study/paired.csv").exists()  # no stale blocks of other runs left beside the table
    # report.columns: a pair loses its block with either of its columns
    table, _, _ = report(path, [*args, "report.columns=[C,B]", f"report.out_dir={tiny / 'cols'}"])
    assert [(p.a.key, p.b.key) for p in table.pairs] == [("C", "B")]


def test_an_also_average_row_averages_only_its_sets_in_the_table_and_the_paired_blocks(tiny):
    """Set Two is category Small (meshes 3, 4: copies of 1, 2) where A (pred2) labels every face right, 100,
    against 83.33 on One: the average over Two alone is 100, not the mean over both sets (91.67). C, on One
    only, has nothing of Two to compare."""
    small = tiny / "db/Small"
    small.mkdir()
    for new, old in (("3", "1"), ("4", "2")):
        (small / f"{new}.off").write_text((tiny / f"db/Tiny/{old}.off").read_text())
        (small / f"{new}_labels.txt").write_text((tiny / f"db/Tiny/{old}_labels.txt").read_text())
        (tiny / "pred2" / f"{new}.lab").write_text((tiny / f"db/Tiny/{old}_labels.txt").read_text())
    (tiny / "pred/3.lab").write_text("body\n1 2\n")
    (tiny / "pred/4.lab").write_text("head\n1 2 3\n")
    cols = [labellings(tiny, "A", "pred2"), labellings(tiny, "B", "pred"), labellings(tiny, "C", "pred2", sets=["One"])]
    sets = [{"name": "One", "category": "Tiny", "published": [90.0] * 3}]
    sets.append({"name": "Two", "category": "Small", "published": [91.0] * 3})
    path = tiny_manifest(tiny, "study", cols, sets, 90.5, paired=[["A", "B"], ["C", "B"]])
    doc = yaml.safe_load(path.read_text())
    doc["groups"][0]["also_average"] = [{"label": "Average (Two)", "sets": ["Two"]}]
    path.write_text(yaml.safe_dump(doc))
    args = [*run_args(tiny), "report.log=false", "report.n_boot=400", "report.results=null"]
    table, _, _ = report(path, [*args, f"report.out_dir={tiny / 'out'}"])  # never the checkout's reports/
    assert [r.label for r in table.rows] == ["One", "Two", "Average", "Average (Two)"]
    one, two, everything, only_two = ([c.value for c in r.cells[:2]] for r in table.rows)
    assert one[0] == pytest.approx(250 / 3) and two == pytest.approx([100.0, two[1]]) and two[1] < 100
    assert everything[0] == pytest.approx(275 / 3) and only_two == pytest.approx(two)
    assert table.rows[3].cells[0].published is None and table.rows[3].cells[2].status == "n/a"  # C: One only
    ab, cb = table.pairs
    assert [(r.label, r.n_meshes) for r in ab.rows] == [("One", 2), ("Two", 2), ("Average", 4), ("Average (Two)", 2)]
    assert ab.rows[3].value == pytest.approx(ab.rows[1].value) != pytest.approx(ab.rows[2].value)
    assert [r.label for r in cb.rows] == ["One", "Average (1 of 2 sets)"]  # nothing of Two to compare
    doc["groups"][0]["also_average"] = [{"label": "Average (Three)", "sets": ["Three"]}]
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ManifestError, match=r"also_average Average \(Three\): sets \['Three'\] are not sets of"):
        load_manifest(path)


# --- curves: ---------------------------------------------------------------------------------------------


def log_fold_runs(tiny, path: Path, key: str, counts: list[dict], acc: float) -> None:
    """FINISHED fold runs of column `key` on category Tiny, found by the config hash the report computes, each
    logging `counts` (one dict per leave-one-out fold) and `acc` on its test mesh."""
    from meshseg.config import run_config
    from meshseg.data.datasets import build_dataset
    from meshseg.data.splits import folds_for
    from meshseg.tracking import fold_identity

    m = load_manifest(path)
    (column,) = [c for c in m.columns if c.key == key]
    cfg = run_config([*m.cell_overrides(m.groups[0], column), *run_args(tiny)])
    resolved = OmegaConf.to_container(cfg, resolve=True)
    dataset = build_dataset(cfg.dataset)
    tracker = Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir)
    for fold, n in zip(folds_for(dataset, "Tiny", cfg.split), counts, strict=True):
        _, chash = fold_identity(resolved, "Tiny", fold, dataset.data_hash)
        table = tiny / f"{chash}/per_mesh.csv"
        table.parent.mkdir()
        table.write_text("mesh,faces,area,acc_raw,acc\n" + "".join(f"{m},2,1.0,{acc},{acc}\n" for m in fold.test))
        with tracker.run(f"{key} {fold.index}", {"config_hash": chash}, n) as run_id:
            tracker.client.log_artifact(run_id, str(table))


def test_the_learning_curve_places_each_cell_at_its_runs_samples_seen(tiny):
    """1B at 3 and 2 samples x 15 epochs (x = 37.5), 1B_4k (set Two only) at 12 x 15 and 8 x 16 (x = 154):
    the points' x are the runs' n_train_samples x n_epochs, their mean over the cell's runs."""
    cols = [
        {"key": "1B", "label": "1B", "overrides": ["model=cnn1d", "branches=1"]},
        {"key": "1B_4k", "label": "1B 4k", "overrides": ["model=cnn1d", "branches=1", "budget.faces_per_mesh=4000"]},
    ]
    cols[1]["sets"] = ["Two"]
    path = study(tiny, cols, curves={"x": "samples", "series": {"1B": ["1B", "1B_4k"]}})
    one = [{"n_train_samples": 3, "n_epochs": 15}, {"n_train_samples": 2, "n_epochs": 15}]
    four = [{"n_train_samples": 12, "n_epochs": 15, "n_train_distinct": 20}, {"n_train_samples": 8, "n_epochs": 16}]
    log_fold_runs(tiny, path, "1B", one, 0.9)
    log_fold_runs(tiny, path, "1B_4k", four, 0.95)
    table = collect(load_manifest(path), run_args(tiny), boot=Bootstrap(50))
    panels = curve_panels(table)
    assert [p.set for p in panels] == ["One", "Two"]
    assert [(q.column, q.x, q.value) for q in panels[0].lines["1B"]] == [("1B", 37.5, pytest.approx(90.0))]
    assert [(q.column, q.x) for q in panels[1].lines["1B"]] == [("1B", 37.5), ("1B_4k", 154.0)]
    assert panels[1].lines["1B"][1].value == pytest.approx(95.0)
    assert [p.published for p in panels] == [{"1B": 90.0}, {"1B": 91.0}]  # the series' first column's
    out = tiny / "out"
    assert out / "learning_curve.png" in write_report(table, out)
    budget = "Budget: cpu (1000 training faces per mesh, 15 epochs | 4000 training faces per mesh, 15 epochs);"
    assert budget in (out / "table.md").read_text()  # both budgets the columns train on, not the last one
    import matplotlib.image

    png = matplotlib.image.imread(out / "learning_curve.png")
    assert png.ndim == 3 and png[..., :3].std() > 0.05

    # x: distinct = the faces any epoch trained on; a run from before n_train_distinct counts n_train_samples
    curves = {"x": "distinct", "series": {"1B": ["1B", "1B_4k"]}}
    distinct = collect(load_manifest(study(tiny, cols, curves=curves)), run_args(tiny), boot=Bootstrap(50))
    (p,) = [p for p in curve_panels(distinct) if p.set == "Two"]
    assert [q.x for q in p.lines["1B"]] == [2.5, 14.0]
    # no `curves:`, no figure
    plain = collect(load_manifest(study(tiny, cols)), run_args(tiny), boot=Bootstrap(50))
    assert curve_panels(plain) == [] and not any(
        f.name == "learning_curve.png" for f in write_report(plain, tiny / "p")
    )
    assert np.isclose(table.rows[1].cells[1].value, 95.0)


# --- a figure the paper printed only as an image (no published number): its bar chart ----------------------


def test_a_table_with_no_published_number_is_drawn_as_bars_with_intervals(tiny):
    """The CF figure's shape (experiments/figure_cf_rf_loo.yaml): per set, then the average, one bar per column
    at the cell's value with its interval as the error bar; the sets the paper printed no number for."""
    from meshseg.report.write import comparison_figure

    columns = [labellings(tiny, "A", "pred"), labellings(tiny, "B", "pred2")]
    sets = [{"name": n, "category": "Tiny", "published": [None, None]} for n in ("One", "Two")]
    table = collect(
        load_manifest(tiny_manifest(tiny, "bars", columns, sets, None)), run_args(tiny), boot=Bootstrap(200)
    )
    (ax,) = comparison_figure(table).axes
    assert [t.get_text() for t in ax.get_xticklabels()] == ["One", "Two", "Average"]
    cells = {(r.label, c.column.key): c for r in table.rows for c in r.cells}
    bars = [(p.get_x() + p.get_width() / 2, p.get_height()) for p in ax.patches]
    # column A's three bars, then B's: heights the cells' values (A: 80 and 66.67 per mesh; B: 100 and 66.67)
    assert [h for _, h in bars] == pytest.approx([cells[(r, k)].value for k in "AB" for r in ("One", "Two", "Average")])
    assert cells[("One", "A")].value == pytest.approx((80 + 200 / 3) / 2)
    assert bars[2][0] - bars[1][0] == pytest.approx(1.5)  # a gap before the average
    (a_err, _) = [c for c in ax.containers if hasattr(c, "errorbar") and c.errorbar]
    (segments,) = [lc.get_segments() for lc in a_err.errorbar.lines[2]]
    got = [y for s in segments for y in s[:, 1]]
    assert got == pytest.approx([y for r in ("One", "Two", "Average") for y in cells[(r, "A")].ci])
