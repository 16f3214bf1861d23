"""experiments/figures.yaml and `python -m meshseg.report <figures file>`: the paper's figures of meshes drawn
from the runs' per-face labels (meshseg/report/figures.py)."""

import io
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import REPO, SMOKE, smoke_env

from meshseg.errors import ManifestError
from meshseg.render import label_colors
from meshseg.report.config import compose_config
from meshseg.report.figures import PANEL, figures_from_config, load_figures, pick_meshes, verify_command
from meshseg.report.manifest import load_manifest
from meshseg.report.table import collect
from meshseg.results import export, import_records, load_records, write_record
from meshseg.tracking import Tracker

ACC = {"3": 90.0, "1": 80.0, "2": 95.0, "10": 80.0, "5": 99.0}


def test_each_rule_picks_the_meshes_it_names():
    ids = list(ACC)
    assert pick_meshes("first", 2, {}, ids) == ["1", "2"]  # ids in number order, not text order ("10" < "2")
    assert pick_meshes("lowest", 2, ACC, ids) == ["1", "10"]  # 80 and 80: the tie by id
    assert pick_meshes("lowest", 1, ACC, ids) == ["1"]
    assert pick_meshes("median", 1, ACC, ids) == ["3"]  # 80 80 [90] 95 99
    assert pick_meshes("median", 2, {k: v for k, v in ACC.items() if k != "5"}, ids) == ["3", "10"]  # lower median
    assert pick_meshes("largest_gap", 2, ACC, ids) == ["2", "5"]  # the two largest values, shown in id order


def test_the_shipped_figures_file_names_real_columns_and_sets():
    figures = load_figures(REPO / "experiments/figures.yaml")
    assert [f.key for f in figures.figures] == [
        "results_over95",
        "cnn1d_vs_tog15",
        "under90",
        "omitted_truth",
        "cf_maps",
        "tog15_image",
    ]
    for f in figures.figures:
        if f.table:
            manifest = load_manifest(REPO / "experiments" / f"{f.table}.yaml")
            assert set(f.rows) - {"truth"} <= {c.key for c in manifest.columns}
            assert set(f.sets) <= {s.name for g in manifest.groups for s in g.sets}


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        ({"pick": "best"}, "pick 'best' is not one of median, lowest, largest_gap, first"),
        ({"colour": 1}, "figure 'f': unknown key 'colour': a figure takes key, "),
        ({"table": "no_such_table"}, "table 'no_such_table': no no_such_table.yaml beside"),
        ({"rows": ["truth"], "pick": "median"}, "pick median needs a run row"),
        ({"pick": "largest_gap"}, "largest_gap needs two run rows"),
        ({"meshes": 0}, "meshes must be a whole number >= 1"),
    ],
)
def test_a_bad_figure_is_one_error_naming_the_file(tmp_path, edit, message):
    shutil.copy(REPO / "experiments/synthetic.yaml", tmp_path)
    figure = {"key": "f", "kind": "labels", "caption": "c", "table": "synthetic", "rows": ["rf"], "sets": ["Cup"]}
    path = tmp_path / "figs.yaml"
    path.write_text(yaml.safe_dump({"name": "figs", "figures": [{**figure, **edit}]}))
    with pytest.raises(ManifestError) as e:
        load_figures(path)
    assert str(e.value).startswith(str(path)) and message in str(e.value)


def png_pixels(data: bytes) -> np.ndarray:
    from matplotlib.image import imread

    return (imread(io.BytesIO(data), format="png")[:, :, :3] * 255).round().astype(int)


def figures_file(tmp_path: Path, figures: list[dict], overrides=()) -> Path:
    shutil.copy(REPO / "experiments/synthetic.yaml", tmp_path)
    path = tmp_path / "figs.yaml"
    path.write_text(yaml.safe_dump({"name": "figs", "overrides": list(overrides), "figures": figures}))
    return path


def test_a_labels_figure_draws_the_runs_labels_and_names_runs_without_them(smoke_store, tmp_path, cache_dir):
    """On the smoke store: the meshes the rule picks, each run's accuracy printed, the labels' colours drawn;
    then the same runs without per-face labels: blank panels and the verify command that gives them labels."""
    env = smoke_env(smoke_store.parent, cache_dir)
    figure = {
        "key": "rf_vs_3b",
        "kind": "labels",
        "caption": "RF against 3B",
        "table": "synthetic",
        "rows": ["truth", "3B", "rf"],
        "sets": ["Cup"],
        "pick": "lowest",
    }
    path = figures_file(tmp_path, [figure])
    args = [*SMOKE, f"report.out_dir={tmp_path / 'out'}", "report.results=null"]
    with pytest.MonkeyPatch.context() as m:
        for k, v in env.items():
            m.setenv(k, v)
        _, [drawn], files = figures_from_config(compose_config("report", path, args))
        frame = collect(load_manifest(tmp_path / "synthetic.yaml"), SMOKE, sets=["Cup"]).meshes
    [shown] = drawn.shown
    assert shown["set"] == "Cup" and not drawn.missing_labels and not drawn.blank
    rf = frame[frame["column"] == "rf"].set_index("mesh")["acc"]
    assert shown["mesh"] == min(rf.index, key=lambda m: (rf[m], int(m)))  # the lowest RF mesh
    assert shown["rf"] == pytest.approx(rf[shown["mesh"]]) and shown["rf run"] in frame["config_hash"].values
    md = (tmp_path / "out/figs/figures.md").read_text()
    assert f"| Cup | {shown['mesh']} | {shown['3B']:.2f} | {shown['rf']:.2f} |" in md
    pixels = png_pixels(files[0].read_bytes())
    assert pixels.shape[0] >= 3 * PANEL  # three rows of panels (truth, 3B, RF) of one mesh
    colours = {tuple(c) for c in pixels.reshape(-1, 3)}
    for c in label_colors(2):  # the cup's two labels in their legend colours (the legend's patches are flat)
        assert tuple(np.round(255 * c).astype(int)) in colours

    bare = tmp_path / "bare"  # the same runs, imported from records without labels (as exported before 2026-12-02)
    smoke = Tracker(f"sqlite:///{smoke_store}/mlflow.db", "meshseg", str(smoke_store / "artifacts"))
    export(smoke, tmp_path / "records")
    for p, record in load_records(tmp_path / "records"):
        write_record(p, {k: v for k, v in record.items() if k != "labels"})
    import_records(
        Tracker(f"sqlite:///{bare}/mlruns/mlflow.db", "meshseg", str(bare / "mlruns/artifacts")), tmp_path / "records"
    )
    with pytest.MonkeyPatch.context() as m:
        for k, v in smoke_env(bare, cache_dir).items():
            m.setenv(k, v)
        _, [drawn], _ = figures_from_config(compose_config("report", path, args))
    assert len(drawn.missing_labels) == 2  # the 3B and RF runs that tested the picked mesh
    md = (tmp_path / "out/figs/figures.md").read_text()
    assert verify_command(drawn.missing_labels) in md and "attach=true" in md


def test_feature_figures_map_the_cached_columns(tmp_path, cache_dir, monkeypatch):
    """A CF map and a ToG15-style image of the synthetic meshes' features, drawn from the feature cache."""
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(cache_dir))
    monkeypatch.setenv("MESHSEG_LOG_DIR", str(tmp_path / "logs"))
    figures = [
        {"key": "cf", "kind": "feature_map", "caption": "c", "features": "cf0_1", "rows": ["cf0", "cf1"]}
        | {"sets": ["Cup"], "meshes": 2},
        {"key": "img", "kind": "feature_image", "caption": "c", "features": "cf0_5", "sets": ["Cup"]}
        | {"shape": [2, 3], "face": 4},
    ]
    path = figures_file(tmp_path, figures, ["dataset=synthetic"])
    _, drawn, files = figures_from_config(compose_config("report", path, [f"report.out_dir={tmp_path}"]))
    assert [d.shown for d in drawn] == [
        [{"set": "Cup", "mesh": m} for m in pick_meshes("first", 2, {}, [e["mesh"] for e in drawn[0].shown])],
        [{"set": "Cup", "mesh": drawn[0].shown[0]["mesh"], "face": 4}],
    ]
    assert [f.name for f in files] == ["cf.png", "img.png", "figures.md"]
    cf = png_pixels(files[0].read_bytes())
    assert cf.shape[0] > 2 * PANEL and len({tuple(c) for c in cf.reshape(-1, 3)}) > 50  # two rows of colour maps
    shape = dict(figures[1], shape=[4, 4])
    path = figures_file(tmp_path, [shape], ["dataset=synthetic"])
    with pytest.raises(ManifestError, match="cf0_5 has 6 columns .* shape 4 x 4 and face 4 do not fit"):
        figures_from_config(compose_config("report", path, [f"report.out_dir={tmp_path}"]))
