"""A manifest column scored from labellings on disk (Kalogerakis 2010's format), and the paired comparison of
two columns: a hand-made two-mesh L-PSB folder, accuracies computed by hand."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import tiny_manifest, tiny_psb

from meshseg.data.datasets import PSB
from meshseg.report.aggregate import Bootstrap, compare
from meshseg.report.manifest import Predictions, load_manifest
from meshseg.report.predictions import score
from meshseg.report.table import collect


@pytest.fixture
def tiny(tmp_path):
    """An L-PSB-shaped folder (category Tiny, meshes 1 and 2) and a folder of labellings of them."""
    tiny_psb(tmp_path)
    pred = tmp_path / "pred"
    pred.mkdir()
    (pred / "1.lab").write_text("body\n1 2\n")  # face 1 wrong (area 1/2 of 5/2), face 2 right: 4/5
    (pred / "2.lab").write_text("head\n1\nbody\n2 3\n")  # face 2 wrong (1/3 of the area): 2/3
    return tmp_path


def test_labellings_on_disk_are_scored_by_area(tiny):
    got = score(Predictions(str(tiny / "pred"), "psb_labels"), PSB(str(tiny / "db")), "Tiny", ["1", "2"], str(tiny))
    assert [m for m, _ in got] == ["1", "2"]
    assert np.allclose([a for _, a in got], [80.0, 200 / 3])


def test_a_label_the_category_lacks_is_named(tiny):
    (tiny / "pred/2.lab").write_text("tail\n1 2 3\n")
    with pytest.raises(ValueError, match=r"pred/2.lab: labels \['tail'\] are not in Tiny's"):
        score(Predictions(str(tiny / "pred"), "psb_labels"), PSB(str(tiny / "db")), "Tiny", ["2"], str(tiny))


def test_a_missing_predictions_path_is_named_as_such(tiny):
    """Issue 48, 10: it was reported as a missing "dataset root"."""
    spec = Predictions(str(tiny / "nowhere.tar.xz"), "psb_labels")
    with pytest.raises(ValueError, match=r"nowhere.tar.xz: predictions.path does not exist \(give a folder or an"):
        score(spec, PSB(str(tiny / "db")), "Tiny", ["1"], str(tiny))


def manifest(tiny, columns) -> object:
    return load_manifest(tiny_manifest(tiny, "tiny", columns, [{"name": "Tiny", "published": [None] * len(columns)}]))


def test_a_predictions_column_in_a_report_and_its_paired_comparison(tiny, monkeypatch):
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tiny / "cache"))
    spec = {"path": str(tiny / "pred"), "format": "psb_labels"}
    m = manifest(
        tiny, [{"key": "K", "label": "K", "predictions": spec}, {"key": "K2", "label": "K2", "predictions": spec}]
    )
    table = collect(m, [f"paths.mlflow_dir={tiny / 'mlruns'}"], paired=("K", "K2"), boot=Bootstrap(200))
    tiny_row, average = table.rows
    cell = tiny_row.cells[0]
    assert cell.status == "ok" and cell.folds == 2  # leave-one-out: 2 folds
    assert list(table.meshes.loc[table.meshes["column"] == "K", "mesh"]) == ["1", "2"]
    assert cell.value == pytest.approx((80 + 200 / 3) / 2)
    assert average.cells[0].value == pytest.approx(cell.value)
    # two identical columns: every per-mesh difference is 0, and so is the whole interval
    for r in table.paired.rows:
        assert r.value == 0.0 and r.ci == (0.0, 0.0) and r.n_meshes == 2


def test_paired_differences_are_per_mesh(tiny, monkeypatch):
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tiny / "cache"))
    other = tiny / "pred2"
    other.mkdir()
    (other / "1.lab").write_text("head\n1\nbody\n2\n")  # all right: 100
    (other / "2.lab").write_text("head\n1 2 3\n")  # face 3 wrong: 2/3
    cols = [
        {"key": "A", "label": "A", "predictions": {"path": str(other), "format": "psb_labels"}},
        {"key": "B", "label": "B", "predictions": {"path": str(tiny / "pred"), "format": "psb_labels"}},
    ]
    table = collect(
        manifest(tiny, cols), [f"paths.mlflow_dir={tiny / 'mlruns'}"], paired=("A", "B"), boot=Bootstrap(500)
    )
    (s, avg) = table.paired.rows
    assert s.value == pytest.approx(((100 - 80) + (200 / 3 - 200 / 3)) / 2)  # 10 points
    assert s.ci[0] <= 0.0 + 1e-9 and s.ci[1] == pytest.approx(20.0)  # resamples of {20, 0}: 0 .. 20
    assert avg.value == pytest.approx(s.value)
    with pytest.raises(ValueError, match=r"report.paired: 'C' is no column of tiny"):
        collect(manifest(tiny, cols), [f"paths.mlflow_dir={tiny / 'mlruns'}"], paired=("A", "C"))


def test_a_column_still_running_is_compared_on_its_finished_folds(tiny, monkeypatch):
    """Table 1's 1D CNN column fills over weeks: each set is compared on the meshes its finished folds
    tested, marked partial, and no average is claimed until every set is complete."""
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tiny / "cache"))
    other = tiny / "pred2"
    other.mkdir()
    (other / "1.lab").write_text("head\n1\nbody\n2\n")  # all right: 100 (B scores 80)
    (other / "2.lab").write_text("head\n1 2 3\n")  # 2/3, as B
    cols = [
        {"key": "A", "label": "A", "predictions": {"path": str(other), "format": "psb_labels"}},
        {"key": "B", "label": "B", "predictions": {"path": str(tiny / "pred"), "format": "psb_labels"}},
    ]
    table = collect(manifest(tiny, cols), [f"paths.mlflow_dir={tiny / 'mlruns'}"], boot=Bootstrap(200))
    # as a run column with the fold of mesh 2 still to run: A's cell misses fold 1, its mesh 2 not scored
    tiny_row, average = table.rows
    a = replace(tiny_row.cells[0], missing=(1,))
    meshes = table.meshes[~((table.meshes["column"] == "A") & (table.meshes["mesh"] == "2"))]
    table = replace(table, rows=(replace(tiny_row, cells=(a, *tiny_row.cells[1:])), average), meshes=meshes)
    (s, avg) = compare(table, "A", "B", Bootstrap(200)).rows
    assert s.n_meshes == 1 and s.value == pytest.approx(20.0) and s.ci == pytest.approx((20.0, 20.0))
    assert s.partial == "A 1 of 2 folds"
    assert avg.value is None and avg.why == "not every set compared"
    table = replace(table, meshes=meshes[meshes["column"] != "A"])  # nothing finished yet: nothing to compare
    (s, _) = compare(table, "A", "B", Bootstrap(200)).rows
    assert s.value is None and s.why == "A: incomplete, B: ok"


@pytest.mark.parametrize("metric", ["acc", "acc_raw"])
def test_where_a_labellings_columns_errors_lie_and_why_it_is_left_out_before_refinement(metric, tiny, monkeypatch):
    """report.boundaries reads a labellings column under acc (wrong area 100 − its accuracy a mesh); under acc_raw
    it has no argmax to read, and the block's aside says so rather than blaming missing per-face labels."""
    from meshseg.report.boundaries import where_errors_lie
    from meshseg.report.write import markdown

    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tiny / "cache"))
    m = manifest(
        tiny, [{"key": "K", "label": "K", "predictions": {"path": str(tiny / "pred"), "format": "psb_labels"}}]
    )
    store = [f"paths.mlflow_dir={tiny / 'mlruns'}"]
    table = collect(m, store, metric=metric, boot=Bootstrap(50))
    frame, unlabelled, raw_files = where_errors_lie(table, store)
    md = markdown(replace(table, boundaries=(frame, unlabelled, raw_files)))
    if metric == "acc":
        assert unlabelled == raw_files == 0 and list(frame["mesh"]) == ["1", "2"]
        assert np.allclose(frame["err"], [20.0, 100 / 3])
        assert "left out" not in md
    else:
        assert (unlabelled, raw_files) == (0, 2) and frame.empty
        assert "2 test meshes left out: 2 from labellings on disk, which have no argmax before refinement" in md
        assert "without per-face labels" not in md
