"""A table read straight from results records (`collect_records`, `runs.records_mesh_table`): the same table as
from a store holding those runs, without importing them."""

import json
import logging

import pandas as pd
import pytest
from conftest import REPO, SMOKE, smoke_env

from meshseg.report import collect, collect_records, load_manifest
from meshseg.report.aggregate import Bootstrap, compare
from meshseg.report.runs import RUN_COLUMNS, records_mesh_table
from meshseg.report.write import csv_text, markdown, refinement_csv
from meshseg.results import export, record_path, write_record
from meshseg.tracking import Tracker


def test_a_table_from_records_is_the_table_from_their_store(smoke_store, tmp_path, cache_dir, monkeypatch):
    export(Tracker(f"sqlite:///{smoke_store}/mlflow.db", "meshseg"), tmp_path / "results")
    manifest = load_manifest(REPO / "experiments/synthetic.yaml")
    boot = Bootstrap(300)
    for k, v in smoke_env(smoke_store.parent, cache_dir).items():  # the same overrides, the store by environment
        monkeypatch.setenv(k, v)
    stored = collect(manifest, SMOKE, boot=boot)
    monkeypatch.setenv("MESHSEG_MLFLOW_DIR", str(tmp_path / "mlruns"))
    shipped = collect_records(tmp_path / "results", manifest, SMOKE, boot=boot)
    assert not (tmp_path / "mlruns").exists()  # no store opened, none made
    assert len(shipped.meshes) == len(stored.meshes) == 3 * 3 * 5  # 3 columns x 3 sets x 5 test meshes
    assert shipped.meshes.drop(columns="run_id").equals(stored.meshes.drop(columns="run_id"))
    for text in (markdown, csv_text, refinement_csv):
        assert text(shipped) == text(stored)
    assert compare(shipped, "3B", "1B", boot) == compare(stored, "3B", "1B", boot)


def record(config_hash: str, fold: int, accs, *, seconds: float = 10.0, **changes) -> dict:
    """A whole results record (one `import` takes) of one fold run of Tiny on test meshes a, b, ... with these
    accuracies (fractions)."""
    meshes = list("abcd"[: len(accs)])
    tags = {"dataset": "psb", "category": "Tiny", "fold": str(fold), "data_hash": "d", "overrides": "[]"}
    tags |= {"fold_ids": json.dumps({"train": ["e"], "test": meshes}), "model": "rf", "config_hash": config_hash}
    tags |= {"branches": "1", "features": "f800", "split": "5fold", "refine": "none", "budget": "cpu"}
    rows = [{"mesh": m, "faces": 2, "area": 1.0, "acc_raw": a - 0.1, "acc": a} for m, a in zip(meshes, accs)]
    counts = {"n_epochs": 1, "n_train_samples": 40, "n_test_faces": 2 * len(rows)}
    doc = {"format": 1, "config_hash": config_hash, "tags": tags, "config": {"category": "Tiny", "fold": fold}}
    means = {"test/acc": sum(accs) / len(accs), "test/acc_raw": sum(a - 0.1 for a in accs) / len(accs)}
    doc |= {"metrics": means, "counts": counts, "per_mesh": rows}
    return doc | {"start_time": 1_000, "end_time": 1_000 + int(1000 * seconds)} | changes


def test_records_give_the_wanted_runs_in_the_wanted_order_and_a_bad_one_is_no_run(tmp_path, caplog):
    hashes = [f"{i:016x}" for i in range(4)]
    records = [
        record(hashes[0], 0, [0.5, 0.75], seconds=12.5),
        record(hashes[1], 1, [1.0]),
        record(hashes[2], 2, [0.25], per_mesh=[{"mesh": "c"}]),  # not whole: `import` would refuse it
        record(hashes[3], 3, [0.5]),  # not wanted
    ]
    for r in records:
        write_record(record_path(tmp_path, r), r)
    wanted = pd.DataFrame({"column": ["x", "x", "y"], "config_hash": [hashes[1], hashes[0], hashes[2]]})
    with caplog.at_level(logging.WARNING, logger="meshseg.report.runs"):
        meshes = records_mesh_table(tmp_path, wanted)
    assert list(meshes.columns) == ["column", *RUN_COLUMNS[:4], "mesh", "acc", "acc_raw"]
    assert list(meshes["config_hash"]) == [hashes[1], hashes[0], hashes[0]]  # wanted's order, then the run's meshes
    assert list(meshes["mesh"]) == ["a", "a", "b"] and list(meshes["acc"]) == [100.0, 50.0, 75.0]
    assert meshes["acc_raw"].tolist() == pytest.approx([90.0, 40.0, 65.0])
    assert meshes["seconds"].tolist() == [10.0, 12.5, 12.5]
    assert meshes["counts"][0] == {"n_train_samples": 40, "n_epochs": 1}  # RUN_COUNTS only
    assert meshes["run_id"][0] == str(record_path(tmp_path, records[1]))  # a record's run is its file
    assert f"{hashes[2]}.json: per_mesh[0] (c)" in caplog.text

    copy = tmp_path / "psb" / "Tiny" / "copy.json"  # a second record of hashes[1]: neither is the run
    write_record(copy, record(hashes[1], 1, [0.0]))
    with caplog.at_level(logging.WARNING, logger="meshseg.report.runs"):
        meshes = records_mesh_table(tmp_path, wanted)
    assert list(meshes["config_hash"]) == [hashes[0], hashes[0]]
    assert f"copy.json: config hash {hashes[1]} is also that of {record_path(tmp_path, records[1])}" in caplog.text


def test_a_store_read_in_place_and_searched_once_gives_the_same_table(smoke_store, cache_dir, monkeypatch):
    from meshseg.report import runs

    manifest = load_manifest(REPO / "experiments/synthetic.yaml")
    boot = Bootstrap(300)
    for k, v in smoke_env(smoke_store.parent, cache_dir).items():
        monkeypatch.setenv(k, v)
    searches, paths = [], []
    search, artifact = runs._search_finished, runs._artifact
    monkeypatch.setattr(runs, "_search_finished", lambda *a: searches.append(a) or search(*a))
    monkeypatch.setattr(runs, "_artifact", lambda c, run, name, tmp: c.download_artifacts(run.info.run_id, name, tmp))
    downloaded = collect(manifest, SMOKE, boot=boot)  # every per-mesh table copied out of the store (the old way)
    monkeypatch.setattr(runs, "_artifact", lambda *a: paths.append(artifact(*a)) or paths[-1])
    with runs.one_search_per_store():
        first, second = collect(manifest, SMOKE, boot=boot), collect(manifest, SMOKE, boot=boot)
    assert len(searches) == 2  # one for the first table, one for both tables within
    assert len(paths) == 2 * 18  # 3 columns x 3 sets x 2 folds a table ...
    assert all(p.startswith(f"{smoke_store}/artifacts/") for p in paths)  # ... each read where the store keeps it
    for table in (first, second):
        assert table.meshes.equals(downloaded.meshes)
        assert markdown(table) == markdown(downloaded)
    collect(manifest, SMOKE, boot=boot)
    assert len(searches) == 3  # outside it, every table searches again
