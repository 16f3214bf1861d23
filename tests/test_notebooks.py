"""The three notebooks execute headlessly, each on the shipped results it is committed with (their numbers checked
against the committed reports), and inspect_run and per_mesh also on the smoke store, whose runs have the
pictures and predictions that records lack. A test's parameters go into a cell inserted after the notebook's
cell tagged `parameters` (papermill's convention); the kernel imports this checkout's meshseg."""

import os
import re
import time

import nbformat
import pytest
from conftest import PSB_ARCHIVE, REPO, SMOKE, require
from nbclient import NotebookClient

NOTEBOOKS = REPO / "notebooks"
#: a cell of the report's table: value [95 % interval]
CELL = re.compile(r"\d+\.\d\d \[\d+\.\d\d, \d+\.\d\d\]")


@pytest.fixture
def kernel_env(cache_dir, monkeypatch):
    """The kernel's environment: this checkout first on its path, the session's cache (archives unpacked once)."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("MESHSEG_CACHE_DIR", str(cache_dir))


def execute(name: str, **params) -> nbformat.NotebookNode:
    """The notebook run from notebooks/ with `params` set after its parameters cell; a cell that errors fails."""
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    at = next(i for i, c in enumerate(nb.cells) if "parameters" in c.metadata.get("tags", []))
    nb.cells.insert(at + 1, nbformat.v4.new_code_cell("\n".join(f"{k} = {v!r}" for k, v in params.items())))
    start = time.monotonic()
    NotebookClient(nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()
    print(f"{name}: {time.monotonic() - start:.1f} s")
    return nb


def outputs(nb) -> str:
    """Every text a cell printed or displayed, and the kinds of images shown."""
    parts = []
    for c in nb.cells:
        for o in c.get("outputs", []):
            parts.append(o.get("text", ""))
            parts += [str(v) for k, v in o.get("data", {}).items() if k.startswith("text/")]
            parts += [k for k in o.get("data", {}) if k.startswith("image/")]
    return "\n".join(parts)


def report_cells(name: str) -> list[str]:
    """The complete cells (value [interval]) of a committed report's table, reports/<name>/table.md."""
    text = (REPO / "reports" / name / "table.md").read_text().split("**Refinement")[0]
    return CELL.findall(text)


def report_row(name: str, row: str) -> dict[str, str]:
    """{column label: value} of the complete cells in one row of a committed report's table."""
    lines = (REPO / "reports" / name / "table.md").read_text().splitlines()
    split = lambda line: [c.strip() for c in line.strip().strip("|").split("|")][1:]
    labels = split(next(line for line in lines if line.startswith("| Set |")))
    cells = split(next(line for line in lines if line.startswith(f"| {row} |")))
    return {k: m.group(0).split()[0] for k, c in zip(labels, cells) if (m := CELL.match(c))}


@pytest.mark.psb
def test_compare_published_shows_table2_as_the_report_does(kernel_env):
    require(PSB_ARCHIVE)
    text = outputs(execute("compare_published.ipynb"))
    cells = report_cells("table2_psb_5fold")
    assert len(cells) >= 51  # 1B, 3B, ToG15: 16 sets and the average each
    assert [c for c in cells if c not in text] == []
    assert "Published: Table 2" in text and "Vase" in text
    assert "1D CNN 3B − 1D CNN 1B" in text and "claim 3" in text  # a paired block, named by the claim it tests
    assert text.count("image/png") >= 3  # the report's figure, Δ per set, the paired blocks


def test_the_committed_notebooks_show_the_committed_reports():
    """The notebooks are committed executed (scripts/execute_notebooks.py): what they show as committed is
    today's results/, so a change of the shipped results that leaves them unexecuted fails here."""
    read = lambda name: outputs(nbformat.read(NOTEBOOKS / name, as_version=4))
    cells = report_cells("table2_psb_5fold")
    assert len(cells) >= 7 * 17  # Table 2's seven columns: 16 sets and the average each
    assert [c for c in cells if c not in read("compare_published.ipynb")] == []
    assert_vase_as_reported(read("per_mesh.ipynb"))


@pytest.mark.psb
def test_inspect_run_shows_what_a_shipped_record_holds(kernel_env, tmp_path):
    require(PSB_ARCHIVE)
    store = tmp_path / "none/mlflow.db"
    text = outputs(execute("inspect_run.ipynb", tracking_uri=f"sqlite:///{store}"))
    assert "Vase f0 · cnn1d 3B f800 · 5fold · cpu" in text and "72.68" in text  # its test/acc, in %
    assert "config hash by this checkout's code: 69a72b753049dbf2 (record: 69a72b753049dbf2)" in text
    assert "390.09" in text  # time/train_s
    assert "No pictures:" in text and not store.parent.exists()  # said plainly, and no store made


def test_inspect_run_shows_the_pictures_a_store_holds(kernel_env, smoke_store, tmp_path):
    from meshseg.results import record_of, record_path, write_record
    from meshseg.tracking import Tracker

    uri = f"sqlite:///{smoke_store}/mlflow.db"
    tracker = Tracker(uri, "meshseg")
    run = tracker.runs("tags.model = 'cnn1d' and attributes.status = 'FINISHED'")[0]
    exported = record_of(tracker, run)  # as `meshseg.results export` writes it
    write_record(path := record_path(tmp_path, exported), exported)
    text = outputs(execute("inspect_run.ipynb", record=str(path), tracking_uri=uri))
    assert "No pictures" not in text
    assert "confusion.png" in text and "renders/" in text and text.count("image/png") >= 4  # + 2 plots


def assert_vase_as_reported(text: str) -> None:
    """per_mesh's output holds every method of Vase's rows in Tables 2 and 1, each at its report's value."""
    # both reports have a ToG15 column: one method per report and column, not per label
    vase = [*report_row("table2_psb_5fold", "Vase").items(), *report_row("table1_psb_loo", "Vase").items()]
    assert {"1D CNN 3B", "ToG15", "Kalogerakis 2010"} <= {label for label, _ in vase}
    assert f"20 meshes x {len(vase)} methods" in text
    for label, value in vase:  # the methods' cells as the reports have them: "1D CNN 3B (5-fold)  81.84"
        assert re.search(rf"^{re.escape(label)} \([^)\n]*\)\s+{value}\s", text, re.M), (label, value)


@pytest.mark.psb
def test_per_mesh_sets_methods_side_by_side_on_vase(kernel_env, tmp_path):
    require(PSB_ARCHIVE)
    text = outputs(execute("per_mesh.ipynb", tracking_uri=f"sqlite:///{tmp_path}/none/mlflow.db"))
    assert_vase_as_reported(text)
    assert "hard for all" in text and "Not drawn: tracking.uri=" in text  # no store here: said plainly
    assert text.count("image/png") >= 2  # the per-mesh plot, Kalogerakis 2010's labelling from disk


def test_per_mesh_renders_the_predictions_a_store_holds(kernel_env, smoke_store):
    uri = f"sqlite:///{smoke_store}/mlflow.db"
    text = outputs(
        execute(
            "per_mesh.ipynb",
            category="cup",
            manifests=["experiments/synthetic.yaml"],
            overrides=[*SMOKE, f"tracking.uri={uri}"],
            results=None,
            tracking_uri=uri,
        )
    )
    assert "5 meshes x 3 methods" in text and "Not drawn" not in text
    assert text.count("image/png") >= 4  # the per-mesh plot and each method's labelling of the hardest mesh
