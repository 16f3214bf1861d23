"""report.boundaries (meshseg/report/boundaries.py): face rings from the true part boundary on a strip whose
distances are known, the wrong area split by ring, and on the smoke store a report whose every mesh's wrong
area is 100 minus the accuracy the run logged for it (refined, or the argmax under report.metric=acc_raw)."""

import shutil

import numpy as np
import pandas as pd
import pytest
from conftest import REPO, SMOKE, smoke_env

from meshseg.metrics import area_weighted_accuracy
from meshseg.report import report
from meshseg.report.boundaries import BAND_NAMES, boundary_rings, error_by_band, summary

SYNTH = REPO / "experiments/synthetic.yaml"


def strip(n_faces: int) -> np.ndarray:
    """A strip of triangles, each sharing an edge with the next only: its face graph is a path 0-1-2-..."""
    faces = []
    for i in range(n_faces // 2):
        faces += [(2 * i, 2 * i + 2, 2 * i + 1), (2 * i + 1, 2 * i + 2, 2 * i + 3)]
    return np.array(faces)


def test_rings_count_edge_steps_from_the_faces_on_a_label_change():
    faces = strip(12)
    labels = np.array([0] * 5 + [1] * 7)  # the change between faces 4 and 5
    rings = boundary_rings(faces, labels)
    assert rings.tolist() == [4, 3, 2, 1, 0, 0, 1, 2, 3, 4, 5, 6]
    two = np.array([0] * 3 + [1] * 6 + [0] * 3)  # a second change: each face counts to the nearer
    assert boundary_rings(faces, two).tolist() == [2, 1, 0, 0, 1, 2, 2, 1, 0, 0, 1, 2]
    assert np.isinf(boundary_rings(faces, np.zeros(12, int))).all()  # one part: no boundary anywhere


def test_the_wrong_area_splits_by_ring_band_and_sums_to_the_error():
    faces = strip(12)
    truth = np.array([0] * 5 + [1] * 7)
    rings = boundary_rings(faces, truth)
    areas = np.arange(1.0, 13.0)  # face i has area i + 1; 78 in all
    pred = truth.copy()
    pred[[4, 7, 11]] = 1 - pred[[4, 7, 11]]  # wrong at rings 0, 2 and 6
    out = error_by_band(pred, truth, areas, rings)
    assert BAND_NAMES == ("0", "1-2", "3-5", "6+")
    expect = {"err_0": 5 / 78, "err_1-2": 8 / 78, "err_3-5": 0.0, "err_6+": 12 / 78}
    assert out == pytest.approx({"err": 25 / 78 * 100, **{k: 100 * v for k, v in expect.items()}})
    assert out["err"] == pytest.approx(100 * (1 - area_weighted_accuracy(pred, truth, areas)))


def test_a_pairs_line_is_b_minus_a_wrong_area_over_the_meshes_both_have():
    """The pair's line is accuracy a − b: b's wrong area minus a's, by band, on shared meshes only."""

    def row(column, mesh, err, err_0):  # the rest of the error beyond ring 2
        return {
            "group": "g",
            "row": "S",
            "column": column,
            "mesh": mesh,
            "err": err,
            "err_0": err_0,
            "err_1-2": 0.0,
            "err_3-5": 0.0,
            "err_6+": err - err_0,
        }

    frame = pd.DataFrame(
        [row("a", "1", 4.0, 1.0), row("a", "2", 6.0, 3.0), row("b", "1", 1.0, 0.5), row("a", "3", 9.0, 9.0)]
    )
    lines = summary(frame, [("a", "b")]).set_index(["column", "minus"])
    assert lines.loc[("a", ""), "meshes"] == 3 and lines.loc[("a", ""), "err"] == pytest.approx(19 / 3)
    assert lines.loc[("a", "b"), "meshes"] == 1 and lines.loc[("a", "b"), "err"] == pytest.approx(-3.0)
    assert lines.loc[("a", "b"), "err_0"] == pytest.approx(-0.5)


@pytest.mark.parametrize("metric", ["acc", "acc_raw"])
def test_the_report_splits_each_runs_own_errors(metric, smoke_store, tmp_path, cache_dir, monkeypatch):
    """Every smoke-store test mesh gets a line whose wrong area is 100 minus the accuracy its run logged under
    the metric, read back from that run's per-face predictions; bands sum to it; table.md has the block."""
    (tmp_path / "mlruns").mkdir()
    shutil.copy(smoke_store / "mlflow.db", tmp_path / "mlruns/mlflow.db")
    for k, v in smoke_env(tmp_path, cache_dir).items():
        monkeypatch.setenv(k, v)
    out = tmp_path / "reports"
    args = [*SMOKE, "report.boundaries=true", f"report.metric={metric}", f"report.out_dir={out}", "report.log=false"]
    table, files, _ = report(SYNTH, args)
    frame = pd.read_csv(out / "synthetic/boundaries.csv", dtype={"mesh": str})
    logged = table.meshes.set_index(["row", "column", "mesh"])[metric]
    assert len(frame) == len(logged) == 3 * 15  # 3 columns x 3 sets x 5 meshes, each a test mesh once
    for r in frame.itertuples():
        assert r.err == pytest.approx(100 - logged[(r.row, r.column, r.mesh)], abs=1e-3)
    bands = frame[[f"err_{b}" for b in BAND_NAMES]].sum(axis=1)
    assert np.allclose(bands, frame["err"], atol=1e-3)
    md = (out / "synthetic/table.md").read_text()
    assert "**Where the errors lie**" in md and "| RF | 15 |" in md
