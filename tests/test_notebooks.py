"""Both notebooks execute headlessly against the smoke store, with the tracking URI (and manifest)
passed as parameters through the environment."""

import re

import nbformat
import yaml
from conftest import REPO, SMOKE
from nbclient import NotebookClient

NOTEBOOKS = REPO / "notebooks"


def execute(name: str, env: dict, monkeypatch) -> nbformat.NotebookNode:
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    NotebookClient(nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(NOTEBOOKS)}}).execute()
    return nb


def outputs(nb) -> str:
    """Every text a cell printed or displayed, and the kinds of images shown."""
    parts = []
    for c in nb.cells:
        for o in c.get("outputs", []):
            texts = [str(v) for k, v in o.get("data", {}).items() if k.startswith("text/")]
            parts.append(o.get("text", "") + "".join(texts))
            parts += [k for k in o.get("data", {}) if k.startswith("image/")]
    return "\n".join(parts)


def test_compare_published_runs_on_the_smoke_store(smoke_store, tmp_path, cache_dir, monkeypatch):
    doc = yaml.safe_load((REPO / "experiments/synthetic.yaml").read_text())
    for s, pub in zip(doc["groups"][0]["sets"], ([95.0, 50.0, 90.0], [90.0, None, 95.0], [40.0, 30.0, 85.0])):
        s["published"] = pub  # invented numbers, so that the scatter and the Δ bars have points
    manifest = tmp_path / "synthetic.yaml"
    manifest.write_text(yaml.safe_dump(doc))
    nb = execute(
        "compare_published.ipynb",
        {
            "MESHSEG_TRACKING_URI": f"sqlite:///{smoke_store}/mlflow.db",
            "MESHSEG_MANIFEST": str(manifest),
            "MESHSEG_OVERRIDES": " ".join(SMOKE),
            "MESHSEG_CACHE_DIR": str(cache_dir),
        },
        monkeypatch,
    )
    text = outputs(nb)
    assert re.search(r"ok\s+12", text)  # 9 sets + 3 averages, all complete
    assert text.count("image/png") >= 2  # scatter and Δ bars
    assert "Figure" in text and "1D CNN 3B" in text


def test_inspect_run_runs_on_the_smoke_store(smoke_store, cache_dir, monkeypatch):
    nb = execute(
        "inspect_run.ipynb",
        {
            "MESHSEG_TRACKING_URI": f"sqlite:///{smoke_store}/mlflow.db",
            "MESHSEG_RUN_ID": "",
            "MESHSEG_CACHE_DIR": str(cache_dir),
        },
        monkeypatch,
    )
    text = outputs(nb)
    assert text.count("image/png") >= 3  # per-mesh bars, render, confusion matrix
    assert "confusion.png" in text and "renders/mesh_" in text and "test/acc" in text
    assert "data_hash" in text and "config_hash" in text  # every tag FoldRecord.TAGS names
