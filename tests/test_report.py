"""meshseg.report and meshseg.reproduce: the statistics on hand-computed cases, manifest errors, and
on a store made by a budget=smoke sweep (conftest.smoke_store): every format, numbers equal to the
runs' own per-mesh tables, a deleted fold shown as incomplete and refilled by reproduce, the report
logged as a run; and the published numbers the report prints for every paper table, against the LaTeX.
Also the command line (Hydra apps: report.* settings, run overrides, errors) and per-cell bootstrap seeds."""

import csv
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import PSB_ARCHIVE, REPO, SMOKE, require, smoke_env
from mlflow import MlflowClient
from test_manifests import PAPER_TABLES, paper_tex, parse_tabulars

from meshseg.cli import ERROR_EXIT
from meshseg.errors import ConfigError, ManifestError
from meshseg.report import collect, load_manifest, report
from meshseg.report.aggregate import Bootstrap, average_cell, average_row, bootstrap_ci, cell_rng, refinement_gain
from meshseg.report.app import main as report_main
from meshseg.report.cells import Cell, Row, Table, progress
from meshseg.report.config import compose_config, run_overrides, split_argv
from meshseg.report.manifest import Column
from meshseg.report.write import FILES
from meshseg.reproduce import MissingCell, missing_cells, reproduce
from meshseg.reproduce import main as reproduce_main
from meshseg.tracking import FoldRecord, is_fold_run

SYNTH = REPO / "experiments/synthetic.yaml"


def cli(module: str, *args, env: dict, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", module, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=900
    )


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def cell(rows: list[dict], row: str, column: str) -> dict:
    (found,) = [r for r in rows if r["row"] == row and r["column"] == column]
    return found


def runs_of(store: Path, experiment: str = "meshseg", filter_string: str = "") -> list:
    """The experiment's runs but sweeps' parent runs (meshseg.tracking.sweeps)."""
    client = MlflowClient(f"sqlite:///{store}/mlflow.db")
    exp = client.get_experiment_by_name(experiment)
    return [r for r in client.search_runs([exp.experiment_id], filter_string) if is_fold_run(r)] if exp else []


# --- statistics -----------------------------------------------------------------------------------

COL = Column("a", "A", ("model=cnn1d",))


def test_bootstrap_of_a_constant_is_that_constant():
    assert bootstrap_ci([np.full(7, 93.0)], 500, 0.95, np.random.default_rng(0)) == pytest.approx((93.0, 93.0))


def test_bootstrap_interval_brackets_the_mean_and_narrows_with_more_meshes():
    few = np.array([90.0, 100.0] * 4)
    many = np.array([90.0, 100.0] * 100)
    lo, hi = bootstrap_ci([few], 4000, 0.95, np.random.default_rng(1))
    lo2, hi2 = bootstrap_ci([many], 4000, 0.95, np.random.default_rng(1))
    lo3, hi3 = bootstrap_ci([few], 4000, 0.5, np.random.default_rng(1))
    assert lo < 95 < hi and lo2 < 95 < hi2
    assert hi2 - lo2 < (hi - lo) / 3  # the standard error shrinks like 1/sqrt(n): 8 -> 200 meshes
    assert hi3 - lo3 < hi - lo
    assert 90 <= lo and hi <= 100


def test_bootstrap_of_sets_resamples_each_set_and_weighs_sets_equally():
    # set means 100 and 50 -> 75 exactly, whatever is resampled (the pooled mean would be 87.5)
    ci = bootstrap_ci([np.full(3, 100.0), np.full(1, 50.0)], 300, 0.95, np.random.default_rng(0))
    assert ci == pytest.approx((75, 75))


def test_average_row_is_the_mean_of_set_values_and_needs_every_set():
    a = Cell(COL, None, value=100.0, n_meshes=4, folds=2)
    b = Cell(COL, None, value=50.0, n_meshes=1, folds=1)
    samples = [np.full(4, 100.0), np.array([50.0])]
    avg = average_cell(COL, 80.0, [a, b], samples, Bootstrap(200), ("average", "g", "Average", "a"))
    assert avg.status == "ok" and avg.value == pytest.approx(75.0) and avg.delta == pytest.approx(-5.0)
    assert avg.n_meshes == 5 and avg.ci == pytest.approx((75.0, 75.0))
    b2 = Cell(COL, None, folds=5, missing=(1, 3))
    assert b2.status == "incomplete" and b2.why() == "2 of 5 folds missing" and b2.value is None
    avg2 = average_cell(COL, 80.0, [a, b2], samples[:1], Bootstrap(200), ("average", "g", "Average", "a"))
    assert avg2.status == "incomplete" and avg2.value is None and avg2.why() == "1 of 2 sets not complete"
    assert Cell(Column("p", "P", None), 93.0).status == "published"


def test_the_refinement_block_is_refined_minus_raw_mesh_by_mesh():
    """Two sets: the cut adds 2 and 0 points on set s1's meshes, -1 on s2's only mesh; the average row is
    the mean over sets ((1 + -1) / 2 = 0), and the markdown shows raw -> refined for each."""
    from meshseg.report.write import markdown, refinement_csv

    s1 = Cell(COL, None, value=85.0, ci=(80.0, 90.0), n_meshes=2, folds=1)
    s2 = Cell(COL, None, value=70.0, ci=(70.0, 70.0), n_meshes=1, folds=1)
    meshes = pd.DataFrame(
        {"group": "g", "row": ["s1", "s1", "s2"], "column": "a", "fold": [0, 1, 0], "mesh": ["1", "2", "3"]}
        | {"acc": [90.0, 80.0, 70.0], "acc_raw": [88.0, 80.0, 71.0]}  # gains 2, 0 and -1
    )
    manifest = type(
        "M",
        (),
        {
            "columns": (COL,),
            "title": "t",
            "source": "",
            "note": "",
            "name": "m",
            "path": Path("m.yaml"),
            "compared_with": "Published",
        },
    )()
    sets = [Row("s1", "set", "g", (s1,)), Row("s2", "set", "g", (s2,))]
    table = Table(manifest, (), (), "acc", 0.95, meshes=meshes)
    table = replace(table, rows=(*sets, average_row(table, "Average", "average", sets, (None,), Bootstrap(200))))
    gains = refinement_gain(table, "a", Bootstrap(400))
    assert [g.value for g in gains] == pytest.approx([1.0, -1.0, 0.0])
    assert gains[0].ci == pytest.approx((0.0, 2.0)) and gains[1].ci == pytest.approx((-1.0, -1.0))
    assert [g.n_meshes for g in gains] == [2, 1, 3]
    table = replace(table, refinement=((COL, gains),))
    md = markdown(table)
    assert "| s1 | 84.00 → 85.00 (+1.00 [+0.00, +2.00]) |" in md and "| s2 | 71.00 → 70.00 (-1.00" in md
    assert "| **Average** | 77.50 → 77.50 (+0.00" in md and "Sets the refinement raised: A 1 of 2." in md
    assert refinement_csv(table).splitlines()[1].startswith("s1,set,a,84.0000,85.0000,1.0000,0.0000,2.0000,2,")
    # a column without raw accuracies (scored from disk) has no refinement row
    table = replace(table, meshes=meshes.assign(acc_raw=[88.0, 80.0, np.nan]))
    gains = refinement_gain(table, "a", Bootstrap())
    assert gains[1].why == "no raw accuracies" and gains[2].value is None


def test_a_cells_generator_is_its_identitys():
    """Seeded by the report seed and the cell's identity only: the same cell draws the same numbers."""
    draw = lambda seed, *identity: cell_rng(seed, *identity).integers(0, 2**31, 4).tolist()
    a = draw(0, "set", "PSB", "Teddy", "3B")
    assert a == draw(0, "set", "PSB", "Teddy", "3B")
    others = [
        draw(1, "set", "PSB", "Teddy", "3B"),
        draw(0, "set", "PSB", "Teddy", "1B"),
        draw(0, "set", "PSB", "Cup", "3B"),
        draw(0, "average", "PSB", "Teddy", "3B"),
        draw(0, "set", "COSEG", "Teddy", "3B"),
    ]
    assert all(o != a for o in others) and len({tuple(o) for o in others}) == len(others)


def test_missing_cells_are_structured_and_make_their_sweeps():
    gap = Cell(
        COL, None, folds=5, missing=(1, 3), overrides=("dataset=psb", "model=cnn1d", "budget=cpu"), category="Teddy"
    )
    ok = Cell(COL, None, n_meshes=1, folds=1)
    rows = [
        Row("Teddy", "set", "PSB", [gap]),
        Row("Cup", "set", "PSB", [ok]),
        Row("Average", "average", "PSB", [Cell(COL, None, members=[gap, ok])]),
    ]
    (m,) = missing_cells(Table(None, rows, ("budget=cpu",), "acc", 0.95))
    assert m == MissingCell("Teddy", "a", ("dataset=psb", "model=cnn1d", "budget=cpu"), "Teddy", (1, 3))
    assert m.sweep() == ["dataset=psb", "model=cnn1d", "budget=cpu", "category=Teddy", "fold=1,3"]


def test_progress_counts_the_cells_no_run_can_fill_apart():
    """Table 4 has COSEG cells whose data is not here: 'complete' counts the cells runs can fill, and says
    how many more are unavailable."""
    ok = Cell(COL, None, n_meshes=1, folds=1)
    gone = Cell(COL, None, problem="dataset coseg has no category 'Vases'")
    gap = Cell(COL, None, folds=5, missing=(2,), seconds=(60.0, 80.0, 100.0, 120.0))
    rows = [Row("Teddy", "set", "PSB", [ok]), Row("Vases", "set", "COSEG", [gone])]
    done = progress(Table(load_manifest(SYNTH), rows, (), "acc", 0.95))
    assert (done.cells, done.unavailable) == (1, 1)
    assert done.text() == "All 1 cells complete (1 more unavailable: no data here to run them)."
    rows.append(Row("Cup", "set", "PSB", [gap]))
    line = progress(Table(load_manifest(SYNTH), rows, (), "acc", 0.95)).text()
    assert line.startswith("1 of 2 cells complete (1 more unavailable: no data here to run them); 1 fold runs missing.")
    assert "about 90 s on one process" in line  # the one missing fold at the set's median fold time


def test_progress_times_each_sets_missing_folds_at_that_sets_median():
    """Sets cost several-fold different times (classes x boosting rounds): a set's missing folds take its own
    median fold time; a set with no timed fold takes the column's median over all its runs."""
    heavy = Cell(COL, None, folds=5, missing=(3, 4), seconds=(400.0, 420.0, 440.0), category="Armadillo")
    light = Cell(COL, None, n_meshes=5, folds=5, seconds=(100.0,) * 5, category="Cup")
    fresh = Cell(COL, None, folds=5, missing=(0, 1, 2, 3, 4), category="Fish")
    rows = [Row(c.category, "set", "PSB", [c]) for c in (heavy, light, fresh)]
    done = progress(Table(load_manifest(SYNTH), rows, (), "acc", 0.95))
    assert done.fold_seconds == {"A": 100.0}  # the column's median over its 8 timed runs
    assert done.seconds == 2 * 420.0 + 5 * 100.0  # the column's median alone would say 7 x 100
    assert "about 22 min on one process at each set's median fold time so far (the column's where" in done.text()


def test_progress_sums_each_columns_run_time():
    """A finished table says what its runs took, column by column, summed over runs (NaN: a run with no end time)."""
    timed = Cell(COL, None, n_meshes=2, folds=2, seconds=(1500.0, 2100.0, float("nan")))
    other = Column("b", "B", ("model=cnn2d",))
    rows = [Row("Teddy", "set", "PSB", [timed, Cell(other, None, n_meshes=1, folds=1, seconds=(42.0,))])]
    done = progress(Table(load_manifest(SYNTH), rows, (), "acc", 0.95))
    assert done.spent == {"A": (2, 3600.0), "B": (1, 42.0)}
    assert done.text() == "All 2 cells complete. Run time so far, summed over runs: A 1.0 h (2 runs), B 42 s (1 run)."


# --- manifests and settings -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "edit, problem",
    [
        (lambda d: d.update(name="other"), "differs from the file name"),
        (lambda d: d["groups"][0]["sets"][0].update(published=[1.0]), "expected a list of 3 numbers"),
        (lambda d: d["columns"][0].update(overrides=["model cnn1d"]), "key=value"),
        (lambda d: d["groups"][0]["sets"][1].update(published=["x", None, None]), "'x' is not a number"),
        (lambda d: d.pop("columns"), "missing key"),
    ],
)
def test_a_bad_manifest_names_the_file_and_the_problem(tmp_path, edit, problem):
    doc = yaml.safe_load(SYNTH.read_text())
    edit(doc)
    path = tmp_path / "synthetic.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(ManifestError, match=problem) as e:
        load_manifest(path)
    assert str(path) in str(e.value)
    with pytest.raises(ManifestError, match="no such manifest file"):
        load_manifest(tmp_path / "absent.yaml")


def test_report_settings_are_split_from_run_overrides():
    args = ["budget=cpu", "report.sets=[Teddy]", "report.n_boot=10", "tracking.uri=x", "hydra/launcher=joblib"]
    app, run = split_argv(["m.yaml", *args])
    assert app == ["manifest=m.yaml", "report.sets=[Teddy]", "report.n_boot=10", "hydra/launcher=joblib"]
    assert run == ["budget=cpu", "tracking.uri=x", "hydra/launcher=joblib"]  # launcher: for reproduce's sweeps
    cfg = compose_config("report", "m.yaml", args)
    assert cfg.manifest == "m.yaml" and list(cfg.report.sets) == ["Teddy"] and cfg.report.n_boot == 10
    assert run_overrides(cfg) == run and cfg.report.metric == "acc" and "dry_run" not in cfg.report
    assert compose_config("report", "m.yaml", ["report.metric=acc_raw"]).report.metric == "acc_raw"
    assert compose_config("reproduce", "m.yaml", ["report.dry_run=true"]).report.dry_run is True
    with pytest.raises(ConfigError, match="unknown report setting 'nope'.*report.metric, report.n_boot"):
        compose_config("report", "m.yaml", ["report.nope=1"])
    with pytest.raises(ConfigError, match="unknown report setting 'dry_run'"):  # reproduce's alone
        compose_config("report", "m.yaml", ["report.dry_run=true"])


def test_run_overrides_reach_the_runs_verbatim():
    """Whatever a run override holds (quotes, backslashes, brackets, interpolations) arrives unchanged."""
    odd = [
        "a=it's",
        "b=c\\",
        "d=\\'e",
        "features.groups=[curvature,pca,gc]",
        "tracking.uri=sqlite:////x y/m.db",
        "hydra.run.dir=${paths.log_dir}/x",
        'e="q"',
    ]
    assert run_overrides(compose_config("report", "m.yaml", odd)) == odd


@pytest.mark.parametrize(
    "args, problem",
    [
        (
            ["report.metric=f1"],
            r"report.metric=f1 is not allowed: choose acc \(after refinement\), acc_raw \(before refinement\)$",
        ),
        (["report.n_boot=0"], "report.n_boot=0 must be an integer >= 1"),
        (["report.level=95"], "report.level=95 must be a number between 0 and 1"),
        (["report.sets=Teddy"], "report.sets=Teddy must be a list"),
        (["report.paired=[cnn1d]"], r"report.paired=\['cnn1d'\] must be two column keys"),
        (["report.paired=[[3B,1B],[1B]]"], r"must be two column keys, .* or a list of such pairs"),
        (["report.columns=3B"], "report.columns=3B must be a list of column keys"),
        (["report.columns=[]"], r"report.columns=\[\] must be a list of column keys"),
    ],
)
def test_bad_report_settings_are_refused(args, problem):
    from meshseg.report.config import check_config

    with pytest.raises(ConfigError, match=problem):
        check_config(compose_config("report", "m.yaml", args))


# --- errors: the user's as one line, the program's with their traceback ------------------------------------


def in_process(main, argv, tmp_path, monkeypatch):
    """Run a command's main() here (Hydra's logging left alone, its folder under tmp_path); its exit status."""
    monkeypatch.setenv("MESHSEG_LOG_DIR", str(tmp_path / "logs"))
    try:
        main([*argv, "hydra/job_logging=none", "hydra/hydra_logging=none"])
    except SystemExit as e:
        return e.code
    return 0


@pytest.mark.parametrize("main", [report_main, reproduce_main], ids=["report", "reproduce"])
@pytest.mark.parametrize(
    "args, problem",
    [
        (["experiments/absent.yaml"], "experiments/absent.yaml: no such manifest file; the shipped manifests: "),
        (["experiments/absent.yaml", "report.nope=1"], "unknown report setting 'nope'"),
        ([str(SYNTH), "report.metric=f1"], "report.metric=f1 is not allowed"),
        ([str(SYNTH), "report.sets=[Teddy]"], "report.sets: ['Teddy'] name no set of synthetic"),
        (["experiments/claims.yaml", "report.n_boot=0"], "report.n_boot=0"),
    ],
)
def test_a_user_error_is_one_error_line(main, args, problem, tmp_path, monkeypatch, capsys):
    assert in_process(main, args, tmp_path, monkeypatch) == ERROR_EXIT
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1 and problem in err, err
    assert not (tmp_path / "logs").exists()  # refused before Hydra makes the command's log folder


def test_a_run_override_or_a_column_that_does_not_compose_is_named(tmp_path, monkeypatch, capsys):
    assert in_process(report_main, [str(SYNTH), "budgte=cpu"], tmp_path, monkeypatch) == ERROR_EXIT
    err = capsys.readouterr().err.strip()
    assert err.startswith(
        "error: run overrides budgte=cpu hydra/job_logging=none hydra/hydra_logging=none do not "
        f"apply to {SYNTH} group synthetic, column 3B: Could not override 'budgte'."
    )
    assert len(err.splitlines()) == 1
    doc = yaml.safe_load(SYNTH.read_text())
    doc["columns"][1]["overrides"] = ["model=cnn9"]
    (tmp_path / "synthetic.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(ManifestError, match=r"synthetic.yaml: group synthetic, column 1B: .*cnn9"):
        report(tmp_path / "synthetic.yaml", ["budget=smoke", "report.log=false"])
    with pytest.raises(
        ConfigError,
        match=r"report.sets: \['Teddy'\] name no set of synthetic; its sets are "
        r"Table, Cup, Figure$",
    ):
        report(SYNTH, ["report.sets=[Cup,Teddy]", "report.log=false"])


@pytest.mark.parametrize("main", [report_main, reproduce_main], ids=["report", "reproduce"])
@pytest.mark.parametrize("exc", [TypeError, ValueError])
def test_a_programming_error_propagates_with_its_traceback(main, exc, tmp_path, monkeypatch, capsys):
    """A bug (here: the YAML reader raising) is no user error: not `error: ...`, but the exception itself
    (HYDRA_FULL_ERROR=1), or its traceback and exit status 1 (Hydra's own report)."""

    def broken(*a, **k):
        raise exc("bug in the report")

    monkeypatch.setattr("meshseg.report.manifest.yaml.safe_load", broken)
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(exc, match="bug in the report"):
        in_process(main, [str(SYNTH)], tmp_path, monkeypatch)
    monkeypatch.delenv("HYDRA_FULL_ERROR")
    assert in_process(main, [str(SYNTH)], tmp_path, monkeypatch) == 1
    err = capsys.readouterr().err
    assert "Traceback" in err and f"{exc.__name__}: bug in the report" in err and "error: " not in err


def test_a_damaged_run_is_a_user_error_naming_the_run(smoke_store, tmp_path, cache_dir, monkeypatch, capsys):
    """A FINISHED run whose per-mesh table cannot be read stops the report with one line naming the run."""
    for k, v in smoke_env(smoke_store.parent, cache_dir).items():
        monkeypatch.setenv(k, v)

    def gone(path):  # the table as the store keeps it (read in place, or downloaded) cannot be read
        raise OSError(f"{Path(path).name} gone")

    monkeypatch.setattr(FoldRecord, "read_per_mesh", gone)
    assert (
        in_process(
            report_main, [str(SYNTH), *SMOKE, "report.log=false", f"report.out_dir={tmp_path}"], tmp_path, monkeypatch
        )
        == ERROR_EXIT
    )
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    expected = r"error: run \w+ \(.+\): cannot read acc/acc_raw from per_mesh.csv: OSError: per_mesh.csv gone"
    assert re.fullmatch(expected, err), err


# --- on the smoke store ---------------------------------------------------------------------------


def mesh_mean(store: Path, tags: dict, metric: str = "acc") -> float:
    """A cell computed by hand: the runs with these tags, their per_mesh.csv rows, mean of `metric` in %."""
    client = MlflowClient(f"sqlite:///{store}/mlflow.db")
    filt = " and ".join(f"tags.{k} = '{v}'" for k, v in tags.items()) + " and attributes.status = 'FINISHED'"
    accs = []
    for run in runs_of(store, filter_string=filt):
        path = client.download_artifacts(run.info.run_id, "per_mesh.csv")
        accs += [100 * float(r[metric]) for r in read_csv(Path(path))]
    assert len(accs) == 5, tags  # every mesh of the set tested exactly once over the 2 folds
    return float(np.mean(accs))


def test_report_writes_every_format_from_the_runs_and_logs_itself(smoke_store, tmp_path, cache_dir):
    env = {**smoke_env(smoke_store.parent, cache_dir), "MESHSEG_LOG_DIR": str(tmp_path / "logs")}
    (tmp_path / "cwd").mkdir()
    r = cli("meshseg.report", str(SYNTH), *SMOKE, f"report.out_dir={tmp_path}", env=env, cwd=tmp_path / "cwd")
    assert r.returncode == 0, r.stderr[-3000:]
    assert list((tmp_path / "cwd").iterdir()) == []  # Hydra's folder is under paths.log_dir, not the cwd
    (logs,) = (tmp_path / "logs/report").iterdir()
    assert (logs / ".hydra/overrides.yaml").is_file() and (logs / "report.log").is_file()
    out = tmp_path / "synthetic"
    assert all((out / f).stat().st_size > 0 for f in FILES)
    rows = read_csv(out / "table.csv")
    columns = {
        "3B": {"model": "cnn1d", "branches": "3"},
        "1B": {"model": "cnn1d", "branches": "1"},
        "rf": {"model": "rf"},
    }
    md = (out / "table.md").read_text()
    refinement = read_csv(out / "refinement.csv")
    for key, tags in columns.items():
        values = []
        for name, category in (("Table", "table"), ("Cup", "cup"), ("Figure", "figure")):
            c = cell(rows, name, key)
            assert c["status"] == "ok" and c["n_meshes"] == "5" and c["budget"] == "smoke"
            value = float(c["reproduced"])
            assert value == pytest.approx(mesh_mean(smoke_store, {**tags, "category": category}), abs=1e-3)
            assert float(c["ci_low"]) <= value <= float(c["ci_high"])
            assert f"{value:.2f} [" in md
            values.append(value)
            # the refinement block: raw is the runs' own acc_raw, refined the cell's value
            g = cell(refinement, name, key)
            raw = mesh_mean(smoke_store, {**tags, "category": category}, "acc_raw")
            assert float(g["raw"]) == pytest.approx(raw, abs=1e-3) and float(g["refined"]) == pytest.approx(value)
            assert float(g["gain"]) == pytest.approx(value - raw, abs=1e-3) and g["n_meshes"] == "5"
            assert float(g["ci_low"]) <= float(g["gain"]) <= float(g["ci_high"])
        avg = cell(rows, "Average", key)
        assert avg["kind"] == "average" and float(avg["reproduced"]) == pytest.approx(np.mean(values), abs=1e-3)
    tex, html = (out / "table.tex").read_text(), (out / "table.html").read_text()
    assert r"\begin{tabular}" in tex and r"\toprule" in tex and tex.count(r"\\") == 1 + 1 + 4  # 2 header + 4 rows
    assert html.count("<tr") == 2 + 4 and "<table>" in html
    import matplotlib.image

    png = matplotlib.image.imread(out / "comparison.png")
    assert png.ndim == 3 and png.shape[0] > 300 and png.shape[1] > png.shape[0] and png[..., :3].std() > 0.05
    (logged,) = runs_of(smoke_store, "meshseg-reports", "tags.report = 'synthetic'")
    assert logged.info.status == "FINISHED" and logged.info.run_id in r.stdout
    client = MlflowClient(f"sqlite:///{smoke_store}/mlflow.db")
    assert {a.path for a in client.list_artifacts(logged.info.run_id)} == {*FILES, "refinement.csv"}
    assert "**Refinement: raw → refined**" in md and "Sets the refinement raised: 1D CNN 3B " in md
    average_3b = float(cell(rows, "Average", "3B")["reproduced"])
    assert logged.data.metrics["Average.3B"] == pytest.approx(average_3b, abs=1e-3)
    assert logged.data.metrics["cells_ok"] == 12


def test_only_columns_keeps_those_columns_in_that_order_with_their_published_numbers():
    m = load_manifest(SYNTH)
    assert [c.key for c in m.columns] == ["3B", "1B", "rf"]
    picked = m.only_columns(["rf", "3B"])
    assert [c.key for c in picked.columns] == ["rf", "3B"]
    for g, h in zip(m.groups, picked.groups):
        assert h.published_average == (g.published_average[2], g.published_average[0])
        assert [s.published for s in h.sets] == [(s.published[2], s.published[0]) for s in g.sets]
    assert picked.published_total == (m.published_total[2], m.published_total[0])
    for bad in (["3B", "cnn9"], ["3B", "3B"]):
        with pytest.raises(ConfigError, match=r"give distinct column keys of synthetic: 3B, 1B, rf$"):
            m.only_columns(bad)


def test_a_cells_interval_does_not_depend_on_the_other_rows(smoke_store, cache_dir, monkeypatch):
    """Cup's intervals are the same in the full table and with report.sets=[Cup]; another seed moves them."""
    for k, v in smoke_env(smoke_store.parent, cache_dir).items():
        monkeypatch.setenv(k, v)
    manifest = load_manifest(SYNTH)
    cis = lambda table: {(r.label, c.column.key): c.ci for r in table.rows for c in r.cells}
    full = cis(collect(manifest, SMOKE, boot=Bootstrap(300)))
    cup = cis(collect(manifest, SMOKE, sets=["Cup"], boot=Bootstrap(300)))
    reseeded = cis(collect(manifest, SMOKE, sets=["Cup"], boot=Bootstrap(300, seed=1)))
    assert set(cup) == {("Cup", k) for k in ("3B", "1B", "rf")} and len(full) == 12
    assert all(cup[k] == full[k] and cup[k][0] < cup[k][1] for k in cup)
    assert all(reseeded[k] != cup[k] for k in cup)


def test_published_numbers_give_deltas(smoke_store, tmp_path, cache_dir, monkeypatch):
    doc = yaml.safe_load(SYNTH.read_text())
    for s, pub in zip(doc["groups"][0]["sets"], ([90.0, 80.0, None], [91.0, None, 70.5], [50.0, 60.0, 70.0])):
        s["published"] = pub
    doc["groups"][0]["published_average"] = [77.0, None, None]
    path = tmp_path / "synthetic.yaml"
    path.write_text(yaml.safe_dump(doc))
    for k, v in smoke_env(smoke_store.parent, cache_dir).items():
        monkeypatch.setenv(k, v)
    table, files, run_id = report(path, [*SMOKE, f"report.out_dir={tmp_path}", "report.log=false"])
    assert run_id is None
    rows = read_csv(tmp_path / "synthetic/table.csv")
    for row, key, pub in (("Table", "3B", 90.0), ("Cup", "rf", 70.5), ("Figure", "1B", 60.0), ("Average", "3B", 77.0)):
        c = cell(rows, row, key)
        assert float(c["published"]) == pub
        assert float(c["delta"]) == pytest.approx(float(c["reproduced"]) - pub, abs=2e-4)
    assert cell(rows, "Cup", "1B")["published"] == "" and cell(rows, "Cup", "1B")["delta"] == ""
    md = (tmp_path / "synthetic/table.md").read_text()
    table_line = next(line for line in md.splitlines() if line.startswith("| Table |"))
    assert " / 90.00 (" in table_line and " / 80.00 (" in table_line
    assert "/ 50.00 (" in next(line for line in md.splitlines() if line.startswith("| Figure |"))


def test_a_deleted_fold_is_incomplete_and_reproduce_launches_only_it(smoke_store, tmp_path, cache_dir, monkeypatch):
    """On a copy of the store: delete rf/cup fold 1; the cell and the rf average have no number;
    reproduce (dry run first) launches exactly that run, which gives back the same number."""
    (tmp_path / "mlruns").mkdir()
    shutil.copy(smoke_store / "mlflow.db", tmp_path / "mlruns/mlflow.db")  # artifact paths are absolute
    env = smoke_env(tmp_path, cache_dir)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    monkeypatch.chdir(REPO)  # where the printed command is pasted (cli runs there)
    args = [str(SYNTH), *SMOKE, f"report.out_dir={tmp_path / 'reports'}"]
    before = float(cell(read_csv(smoke_report(tmp_path, args)), "Cup", "rf")["reproduced"])
    (victim,) = runs_of(
        tmp_path / "mlruns", filter_string="tags.model = 'rf' and tags.category = 'cup' and tags.fold = '1'"
    )
    MlflowClient(f"sqlite:///{tmp_path}/mlruns/mlflow.db").delete_run(victim.info.run_id)

    rows = read_csv(smoke_report(tmp_path, args))
    c, avg = cell(rows, "Cup", "rf"), cell(rows, "Average", "rf")
    assert (c["status"], c["reproduced"], c["why"], c["folds_missing"]) == (
        "incomplete",
        "",
        "1 of 2 folds missing",
        "1",
    )
    assert (avg["status"], avg["reproduced"], avg["why"]) == ("incomplete", "", "1 of 3 sets not complete")
    assert cell(rows, "Cup", "3B")["status"] == "ok"
    md = (tmp_path / "reports/synthetic/table.md").read_text()
    cup = next(line for line in md.splitlines() if line.startswith("| Cup |"))
    assert cup.split(" | ")[-1].startswith("— (1/2)")  # then the manifest's reference number, if any
    # under the table: what is missing, the command that makes it, and how long that should take
    (line,) = [x for x in md.splitlines() if "cells complete" in x]
    assert line.startswith("8 of 9 cells complete; 1 fold runs missing. Next: `python -m meshseg.reproduce ")
    rf = runs_of(tmp_path / "mlruns", filter_string="tags.model = 'rf'")  # the 5 left
    seconds = np.median([(r.info.end_time - r.info.start_time) / 1000 for r in rf])
    (cup0,) = [r for r in rf if r.data.tags["category"] == "cup"]  # the set's one fold left
    took = re.search(r"about (\d+) s on one process at each set's median .* none: RF (\d+) s\)\. ", line)
    assert took and int(took[2]) == round(seconds)  # the column's median fold time
    assert int(took[1]) == round((cup0.info.end_time - cup0.info.start_time) / 1000)  # the missing fold at Cup's
    # and what the column's finished runs took, summed (the time a finished column reports)
    spent = re.search(r"Run time so far, summed over runs: .*RF (\d+) (s|min) \((\d+) runs\)", line)
    total = sum((r.info.end_time - r.info.start_time) / 1000 for r in rf)
    assert spent and int(spent[3]) == len(rf) == 5
    assert int(spent[1]) == round(total if spent[2] == "s" else total / 60)

    n = len(runs_of(tmp_path / "mlruns", filter_string="attributes.status = 'FINISHED'"))
    pasted = shlex.split(line.split("`")[1])  # the printed command, as a user would paste it
    assert pasted[:3] == ["python", "-m", "meshseg.reproduce"]
    dry = cli("meshseg.reproduce", *pasted[3:], "report.dry_run=true", env=env)
    assert dry.returncode == 0 and "1 cell(s) lack 1 fold run(s)" in dry.stderr and "category=cup fold=1" in dry.stderr
    assert len(runs_of(tmp_path / "mlruns", filter_string="attributes.status = 'FINISHED'")) == n
    r = cli("meshseg.reproduce", *args, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    finished = runs_of(tmp_path / "mlruns", filter_string="attributes.status = 'FINISHED'")
    assert len(finished) == n + 1
    new = [f for f in finished if f.info.run_id not in {x.info.run_id for x in runs_of(smoke_store)}]
    assert [(x.data.tags["model"], x.data.tags["category"], x.data.tags["fold"]) for x in new] == [("rf", "cup", "1")]
    c = cell(read_csv(tmp_path / "reports/synthetic/table.csv"), "Cup", "rf")
    assert c["status"] == "ok" and float(c["reproduced"]) == pytest.approx(before, abs=1e-4)  # same seed, same run


def smoke_report(tmp_path: Path, args: list) -> Path:
    """The report of `args` (manifest, then overrides), made here (the command line is tested above)."""
    report(Path(args[0]), [*args[1:], "report.log=false"])
    return tmp_path / "reports/synthetic/table.csv"


# --- the paper's tables ---------------------------------------------------------------------------


@pytest.mark.parametrize("stem", sorted(PAPER_TABLES))
def test_the_report_prints_the_papers_numbers(stem, tmp_path, cache_dir, monkeypatch):
    """From an empty store: every published cell the report writes equals the LaTeX, row for row,
    and no cell has a reproduced number."""
    require(PSB_ARCHIVE)
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(cache_dir))
    monkeypatch.setenv("MESHSEG_MLFLOW_DIR", str(tmp_path / "mlruns"))

    def not_scored(plan):  # a column from labellings on disk has no published number: not scored here
        return replace(plan, cell=replace(plan.cell, problem="not scored in this test"))

    monkeypatch.setattr("meshseg.report.table._fill_predictions", not_scored)
    path = REPO / f"experiments/{stem}.yaml"
    args = [f"report.out_dir={tmp_path}", "report.log=false", "report.n_boot=10", "report.results=null"]
    report(path, args)
    ours = {c.key for c in load_manifest(path).columns if c.predictions is not None}
    rows = [r for r in read_csv(tmp_path / stem / "table.csv") if r["column"] not in ours]
    printed: dict[str, list] = {}
    for r in rows:
        printed.setdefault((r["group"], r["row"]), []).append(None if r["published"] == "" else float(r["published"]))
    paper = [row for t in parse_tabulars(paper_tex(), PAPER_TABLES[stem]) for row in t]
    extra = 1 if stem == "table4_fixed_splits" else 0  # Table 4's "Testing Meshes" column
    assert [(k[1], v) for k, v in printed.items()] == [(name, values[extra:]) for name, values in paper]
    assert {r["status"] for r in rows} <= {"incomplete", "unavailable", "published"}
    assert not any(r["reproduced"] for r in rows)
    md = (tmp_path / stem / "table.md").read_text()
    name, values = paper[0]
    first = next(line for line in md.splitlines() if line.startswith(f"| {name} |"))
    assert all(
        f"/ {v:.2f}" in first or f"| {v:.2f}" in first or f"{v:.2f} |" in first for v in values[extra:] if v is not None
    )


def test_an_empty_table_2_says_what_is_missing_and_the_command_runs_exactly_that(tmp_path, cache_dir, monkeypatch):
    """Table 2 from an empty store: compact cells, then the count of missing fold runs and a
    `meshseg.reproduce` command that, pasted (dry run), would launch exactly those."""
    require(PSB_ARCHIVE)
    monkeypatch.chdir(REPO)  # the command names the manifest relative to where the report ran
    env = smoke_env(tmp_path, cache_dir)
    for k in ("MESHSEG_CACHE_DIR", "MESHSEG_MLFLOW_DIR"):
        monkeypatch.setenv(k, env[k])
    path = REPO / "experiments/table2_psb_5fold.yaml"
    report(path, [f"report.out_dir={tmp_path}", "report.log=false", "report.n_boot=10", "report.results=null"])
    md = (tmp_path / "table2_psb_5fold/table.md").read_text()
    teddy = next(x for x in md.splitlines() if x.startswith("| Teddy |"))
    # every column: no fold run, then the published number; 1B, 3B and ToG15 are at three training seeds (5 folds each)
    assert teddy.count("— (0/5) /") == 4 and teddy.count("— (0/15 runs) /") == 3
    (line,) = [x for x in md.splitlines() if "cells complete" in x]
    command = "python -m meshseg.reproduce experiments/table2_psb_5fold.yaml report.results=null"
    assert (
        line
        == f"0 of 112 cells complete; 1040 fold runs missing. Next: `{command}` — no fold timed yet to say how long."
    )
    dry = cli("meshseg.reproduce", *shlex.split(command)[3:], "report.dry_run=true", env=env)
    assert dry.returncode == 0, dry.stderr[-2000:]
    # a sweep per (column, set), and per seed for 1B, 3B and ToG15: 4 x 16 + 3 x 16 x 3
    assert "208 cell(s) lack 1040 fold run(s)" in dry.stderr and dry.stderr.count("would run: ") == 208
    assert (
        "[208/208] would run: python -m meshseg.run -m" in dry.stderr and "category=Vase fold=0,1,2,3,4" in dry.stderr
    )
    # report.columns: those columns only, run one after the other in the order given
    picked = reproduce(path, ["report.columns=[ToG15,3B]", "report.dry_run=true", "report.results=null"])
    order = [(c.column, c.row) for c in picked.launched]
    assert len(order) == 96 and order[0] == order[1] == order[2] == ("ToG15", "Airplane")
    # a sweep per seed, for ToG15 and 3B alike
    assert order[47] == ("ToG15", "Vase") and order[48] == order[49] == order[50] == ("3B", "Airplane")
    assert order[-1] == ("3B", "Vase")
    for first in (0, 48):
        assert [c.sweep()[-3] for c in picked.launched[first : first + 3]] == ["seed=0", "seed=1", "seed=2"]
    assert [c.key for c in picked.table.columns] == ["ToG15", "3B"]
    assert picked.table.rows[-1].cells[0].published == 92.04  # ToG15's published average moved with it
    assert "report.columns=[ToG15,3B]" in progress(picked.table).command


def test_headers_carry_no_latex():
    """A manifest's `source` keeps the paper's `\\label{...}` (tests match it against the LaTeX); the
    report's header shows the label's bare name."""
    from meshseg.report.write import header_lines

    manifest = load_manifest(REPO / "experiments/table4_fixed_splits.yaml")
    lines = header_lines(Table(manifest, [], (), "acc", 0.95))
    assert lines[1] == "Published: Table 4 (table:results-1fold)"
    assert not any("\\" in line for line in lines)
