"""A manifest's content checked in full when it is loaded (issue 48): a key outside the schema at any level, a
file that is not UTF-8, a published nan or inf, a pair of a column with itself, two rows of one label; and each
cell's run config checked as meshseg.run checks it, before the table. Each is one error naming the file, the
place and the problem; these tests only load manifests (no run is trained)."""

import re

import pytest
import yaml
from conftest import REPO

from meshseg.cli import ERROR_EXIT
from meshseg.errors import ConfigError, ManifestError
from meshseg.report import collect, load_manifest, report
from meshseg.report.app import main as report_main
from meshseg.reproduce import reproduce

SYNTH = REPO / "experiments/synthetic.yaml"
KNOWN = {
    "manifest": "name, title, source, note, compared_with, overrides, columns, paired, curves, groups, total",
    "column": "key, label, overrides, predictions, sets, seeds",
    "group": "name, overrides, average, published_average, also_average, sets",
    "set": "name, category, published, test_meshes",
}


def synthetic(tmp_path, edit=None):
    """experiments/synthetic.yaml, edited by `edit` (a function of its YAML mapping), as tmp_path/synthetic.yaml."""
    doc = yaml.safe_load(SYNTH.read_text())
    if edit:
        edit(doc)
    path = tmp_path / "synthetic.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def refused(path, problem: str) -> None:
    """load_manifest refuses `path` with exactly `<path>: <problem>`."""
    with pytest.raises(ManifestError, match=f"^{re.escape(f'{path}: {problem}')}$"):
        load_manifest(path)


def quiet(tmp_path, monkeypatch) -> list[str]:
    """The settings that keep a report's store, cache, log and files in tmp_path (should a check let it run), and
    that import no shipped records, as arguments after MANIFEST."""
    for name, folder in (("MLFLOW", "mlruns"), ("CACHE", "cache"), ("LOG", "logs")):
        monkeypatch.setenv(f"MESHSEG_{name}_DIR", str(tmp_path / folder))
    args = ["report.results=null", "report.log=false", f"report.out_dir={tmp_path / 'out'}"]
    return [*args, "hydra/job_logging=none", "hydra/hydra_logging=none"]


def one_error_line(argv, tmp_path, monkeypatch, capsys) -> str:
    """meshseg.report's main() on `argv` in this process: its exit status must be ERROR_EXIT and its stderr one
    `error:` line (no traceback), returned."""
    with pytest.raises(SystemExit) as e:
        report_main([*map(str, argv), *quiet(tmp_path, monkeypatch)])
    err = capsys.readouterr().err.strip()
    assert e.value.code == ERROR_EXIT and err.startswith("error: ") and len(err.splitlines()) == 1, err
    return err


def test_the_unedited_copy_loads(tmp_path):
    assert load_manifest(synthetic(tmp_path)).columns[0].overrides == ("model=cnn1d", "branches=3")


# --- keys outside the schema -----------------------------------------------------------------------------


def _predictions_column(d):
    d["columns"].append({"key": "K", "label": "K", "predictions": {"path": "p", "formt": "psb_labels"}})
    for s in d["groups"][0]["sets"]:
        s["published"].append(None)
    d["groups"][0]["published_average"].append(None)


@pytest.mark.parametrize(
    "edit, problem",
    [
        (lambda d: d.update(paried=[["3B", "1B"]]), f"unknown key 'paried': a manifest takes {KNOWN['manifest']}"),
        (
            lambda d: d["columns"][1].update(overide=d["columns"][1].pop("overrides")),
            f"column 1B: unknown key 'overide': a column takes {KNOWN['column']}",
        ),
        (
            lambda d: d["groups"][0].update(averge="Mean"),
            f"group synthetic: unknown key 'averge': a group takes {KNOWN['group']}",
        ),
        (
            lambda d: d["groups"][0]["sets"][1].update(test_mesh=4),
            f"group synthetic, set Cup: unknown key 'test_mesh': a set takes {KNOWN['set']}",
        ),
        (
            lambda d: d.update(total={"label": "Total", "published": [None] * 3, "note": "x"}),
            "total: unknown key 'note': total takes label, published",
        ),
        (_predictions_column, "column K, predictions: unknown key 'formt': predictions takes path, format"),
        (
            lambda d: d.update(curves={"x": "samples", "serie": {"s": ["1B", "3B"]}}),
            "curves: unknown key 'serie': curves takes x, series",
        ),
        (
            lambda d: d["groups"][0].update(also_average=[{"label": "Two", "set": ["Cup", "Table"]}]),
            "group synthetic, also_average Two: unknown key 'set': an also_average row takes label, sets",
        ),
    ],
    ids=["top", "column", "group", "set", "total", "predictions", "curves", "also_average"],
)
def test_a_key_outside_the_schema_is_refused_naming_the_known_ones(tmp_path, edit, problem):
    refused(synthetic(tmp_path, edit), problem)


def test_a_mistyped_column_key_is_one_error_line_before_anything_runs(tmp_path, monkeypatch, capsys):
    """`overide:` for `overrides:` once made the column published-only: its runs neither counted nor launched."""
    path = synthetic(tmp_path, lambda d: d["columns"][1].update(overide=d["columns"][1].pop("overrides")))
    err = one_error_line([path], tmp_path, monkeypatch, capsys)
    assert err == f"error: {path}: column 1B: unknown key 'overide': a column takes {KNOWN['column']}"
    assert not (tmp_path / "logs").exists()  # refused before Hydra makes the command's log folder


# --- the file and its numbers ----------------------------------------------------------------------------


def test_a_manifest_that_is_not_utf8_is_one_error_line(tmp_path, monkeypatch, capsys):
    path = synthetic(tmp_path)
    path.write_bytes(path.read_bytes().replace(b"Synthetic sets", b"Synth\xe9tic sets"))  # Latin-1
    offset = path.read_bytes().index(b"\xe9")
    refused(path, f"not UTF-8 text: byte 0xe9 at offset {offset}")
    err = one_error_line([path], tmp_path, monkeypatch, capsys)
    assert err == f"error: {path}: not UTF-8 text: byte 0xe9 at offset {offset}"


@pytest.mark.parametrize("value, shown", [(float("nan"), "nan"), (float("inf"), "inf"), (float("-inf"), "-inf")])
def test_a_published_number_must_be_finite(tmp_path, value, shown):
    path = synthetic(tmp_path, lambda d: d["groups"][0]["sets"][0].update(published=[value, None, 99.0]))
    refused(path, f"set Table published: {shown} is not a finite number (null: no published number)")
    path = synthetic(tmp_path, lambda d: d["groups"][0].update(published_average=[99.0, value, None]))
    refused(path, f"group synthetic published_average: {shown} is not a finite number (null: no published number)")


@pytest.mark.parametrize(
    "edit, problem",
    [
        (
            lambda d: d.update(groups=["synthetic"]),
            "groups[0]: a group is a mapping with name and sets, got 'synthetic'",
        ),
        (lambda d: d.update(total="Total"), "total: expected {label: ..., published: [numbers]}, got 'Total'"),
    ],
    ids=["group", "total"],
)
def test_a_part_that_is_no_mapping_is_refused(tmp_path, edit, problem):
    refused(synthetic(tmp_path, edit), problem)


def test_a_pair_of_a_column_with_itself_is_refused(tmp_path):
    path = synthetic(tmp_path, lambda d: d.update(paired=[["3B", "1B"], ["rf", "rf"]]))
    refused(path, "paired: [['rf', 'rf']] pair a column with itself; a pair is two different columns [a, b]")


# --- row labels -------------------------------------------------------------------------------------------


def _second_group(d, name="more", sets=("Vase",), average="Average (more)"):
    sets = [{"name": s, "category": "cup", "published": [None] * 3} for s in sets]
    d["groups"].append({"name": name, "average": average, "published_average": [None] * 3, "sets": sets})


@pytest.mark.parametrize(
    "edit, problem",
    [
        (
            lambda d: d["groups"][0]["sets"][2].update(name="Cup"),
            "group synthetic: two sets are named 'Cup'; each row of a group needs its own label",
        ),
        (
            lambda d: d["groups"][0].update(average="Table"),
            "group synthetic: a set and the average row are both labelled 'Table'; each row of a group needs its "
            "own label",
        ),
        (
            lambda d: d["groups"][0].update(also_average=[{"label": "Average", "sets": ["Cup", "Table"]}]),
            "group synthetic: an also_average row and the average row are both labelled 'Average'; each row of a "
            "group needs its own label",
        ),
        (
            lambda d: (_second_group(d), d.update(total={"label": "Average", "published": [None] * 3})),
            "total: the total row and the average row of group synthetic are both labelled 'Average'",
        ),
        (
            lambda d: (_second_group(d), d.update(total={"label": "Vase", "published": [None] * 3})),
            "total: the total row and a set of group more are both labelled 'Vase'",
        ),
    ],
    ids=["two-sets", "average-is-a-set", "also-average-is-the-average", "total-is-an-average", "total-is-a-set"],
)
def test_two_rows_of_one_label_are_refused(tmp_path, edit, problem):
    refused(synthetic(tmp_path, edit), problem)


def test_groups_may_repeat_each_others_labels_as_table_3_does(tmp_path):
    """Table 3 prints a set Vases and a row Average in each of its blocks: rows are told apart by their group."""
    path = synthetic(tmp_path, lambda d: _second_group(d, sets=("Cup", "Vase"), average="Average"))
    assert [g.average for g in load_manifest(path).groups] == ["Average", "Average"]
    assert len(load_manifest(REPO / "experiments/table3_coseg_5fold.yaml").groups) == 2


# --- each cell's run config, checked as meshseg.run checks it ----------------------------------------------


@pytest.fixture
def store(tmp_path, monkeypatch):
    """Run overrides that keep any store in tmp_path (a refused report should open none)."""
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(tmp_path / "cache"))
    return [f"paths.mlflow_dir={tmp_path / 'mlruns'}"]


@pytest.mark.parametrize(
    "setting, problem",
    [
        ("branches=7", "branches=7 is not allowed: choose one of [1, 2, 3, 4]"),
        ("budget.faces_per_mesh=abc", "budget.faces_per_mesh=abc is not allowed"),
    ],
)
def test_a_column_whose_runs_cannot_start_is_refused_before_the_table(tmp_path, store, setting, problem):
    path = synthetic(tmp_path, lambda d: d["columns"][1]["overrides"].append(setting))
    manifest = load_manifest(path)  # it composes: only meshseg.run's own check refuses it
    where = re.escape(f"{path}: group synthetic, column 1B: {problem}")
    with pytest.raises(ManifestError, match=f"^{where}"):
        collect(manifest, store)
    with pytest.raises(ManifestError, match=f"^{where}"):  # nothing launched, no command offered
        reproduce(path, [*store, "report.dry_run=true", "report.results=null", f"report.out_dir={tmp_path}"])
    assert not (tmp_path / "mlruns").exists()
    shipped = tmp_path / "results"  # records to import: refused before the import opens a store for them
    (shipped / "synthetic" / "Cup").mkdir(parents=True)
    (shipped / "synthetic" / "Cup" / "0123456789abcdef.json").write_text("{}")
    with pytest.raises(ManifestError, match=f"^{where}"):
        report(path, [*store, f"report.results={shipped}", "report.log=false", f"report.out_dir={tmp_path}"])
    assert not (tmp_path / "mlruns").exists()


def test_a_column_whose_runs_cannot_start_is_one_error_line(tmp_path, store, monkeypatch, capsys):
    path = synthetic(tmp_path, lambda d: d["columns"][1]["overrides"].append("branches=7"))
    err = one_error_line([path, *store], tmp_path, monkeypatch, capsys)
    assert err == f"error: {path}: group synthetic, column 1B: branches=7 is not allowed: choose one of [1, 2, 3, 4]"
    assert not (tmp_path / "out").exists()


def test_a_run_override_no_run_can_start_with_is_the_command_lines_fault(tmp_path, store):
    with pytest.raises(
        ConfigError,
        match=re.escape(f"do not apply to {SYNTH} group synthetic, column 3B: branches=7 is not allowed: choose one"),
    ):
        report(SYNTH, [*store, "branches=7", "report.results=null", "report.log=false"])
