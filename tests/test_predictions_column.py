"""A manifest column scored from labellings on disk (Kalogerakis 2010's format), and the paired comparison of
two columns: a hand-made two-mesh L-PSB folder, accuracies computed by hand."""

import numpy as np
import pytest
import yaml

from meshseg.data.datasets import PSB
from meshseg.report.manifest import Predictions, load_manifest
from meshseg.report.predictions import score
from meshseg.report.table import collect

# mesh 1: two triangles of area 1/2 and 2 (a 1 x 1 and a 2 x 2 right triangle); mesh 2: three unit triangles
MESH1 = "OFF\n6 2 0\n0 0 0\n1 0 0\n0 1 0\n5 0 0\n7 0 0\n5 2 0\n3 0 1 2\n3 3 4 5\n"
MESH2 = "OFF\n9 3 0\n" + "".join(f"{x} 0 0\n{x + 1} 0 0\n{x} 1 0\n" for x in (0, 3, 6)) + "3 0 1 2\n3 3 4 5\n3 6 7 8\n"


@pytest.fixture
def tiny(tmp_path):
    """An L-PSB-shaped folder (category Tiny, meshes 1 and 2) and a folder of labellings of them."""
    d = tmp_path / "db/Tiny"
    d.mkdir(parents=True)
    (d / "1.off").write_text(MESH1)
    (d / "1_labels.txt").write_text("head\n1\nbody\n2\n")
    (d / "2.off").write_text(MESH2)
    (d / "2_labels.txt").write_text("head\n1 2\nbody\n3\n")
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


def manifest(tiny, columns) -> object:
    doc = {
        "name": "tiny",
        "title": "t",
        "overrides": ["dataset=psb", f"dataset.root={tiny / 'db'}", "split=loo"],
        "columns": columns,
        "groups": [
            {
                "name": "g",
                "average": "Average",
                "published_average": [None] * len(columns),
                "sets": [{"name": "Tiny", "published": [None] * len(columns)}],
            }
        ],
    }
    path = tiny / "tiny.yaml"
    path.write_text(yaml.safe_dump(doc))
    return load_manifest(path)


def test_a_predictions_column_in_a_report_and_its_paired_comparison(tiny, monkeypatch):
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tiny / "cache"))
    spec = {"path": str(tiny / "pred"), "format": "psb_labels"}
    m = manifest(
        tiny, [{"key": "K", "label": "K", "predictions": spec}, {"key": "K2", "label": "K2", "predictions": spec}]
    )
    table = collect(m, [f"paths.mlflow_dir={tiny / 'mlruns'}"], n_boot=200, paired=("K", "K2"))
    tiny_row, average = table.rows
    cell = tiny_row.cells[0]
    assert cell.status == "ok" and cell.meshes == ("1", "2") and cell.folds == 2  # leave-one-out: 2 folds
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
    table = collect(manifest(tiny, cols), [f"paths.mlflow_dir={tiny / 'mlruns'}"], n_boot=500, paired=("A", "B"))
    (s, avg) = table.paired.rows
    assert s.value == pytest.approx(((100 - 80) + (200 / 3 - 200 / 3)) / 2)  # 10 points
    assert s.ci[0] <= 0.0 + 1e-9 and s.ci[1] == pytest.approx(20.0)  # resamples of {20, 0}: 0 .. 20
    assert avg.value == pytest.approx(s.value)
    with pytest.raises(ValueError, match=r"report.paired: 'C' is no column of tiny"):
        collect(manifest(tiny, cols), [f"paths.mlflow_dir={tiny / 'mlruns'}"], paired=("A", "C"))


def test_a_column_still_running_is_compared_on_its_finished_folds(tiny, monkeypatch):
    """Table 1's 1D CNN column fills over weeks: each set is compared on the meshes its finished folds
    tested, marked partial, and no average is claimed until every set is complete."""
    from meshseg.report.table import compare

    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tiny / "cache"))
    other = tiny / "pred2"
    other.mkdir()
    (other / "1.lab").write_text("head\n1\nbody\n2\n")  # all right: 100 (B scores 80)
    (other / "2.lab").write_text("head\n1 2 3\n")  # 2/3, as B
    cols = [
        {"key": "A", "label": "A", "predictions": {"path": str(other), "format": "psb_labels"}},
        {"key": "B", "label": "B", "predictions": {"path": str(tiny / "pred"), "format": "psb_labels"}},
    ]
    table = collect(manifest(tiny, cols), [f"paths.mlflow_dir={tiny / 'mlruns'}"], n_boot=200)
    a = table.rows[0].cells[0]
    a.missing, a.scored = (1,), a.scored[:1]  # as a run column with the fold of mesh 2 still to run
    (s, avg) = compare(table, "A", "B", n_boot=200).rows
    assert s.n_meshes == 1 and s.value == pytest.approx(20.0) and s.ci == pytest.approx((20.0, 20.0))
    assert s.partial == "A 1 of 2 folds"
    assert avg.value is None and avg.why == "not every set compared"
    a.scored = ()  # nothing finished yet: nothing to compare
    (s, _) = compare(table, "A", "B", n_boot=200).rows
    assert s.value is None and s.why == "A: incomplete, B: ok"
