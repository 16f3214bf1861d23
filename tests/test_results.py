"""Portable results (`meshseg.results`): the smoke store exported to JSON records, imported into an empty store,
and the report rebuilt from the import byte for byte; import is idempotent and refuses stale records."""

import json
import shutil
import tempfile
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import REPO, SMOKE, smoke_env

from meshseg.report import report
from meshseg.results import decode_labels, export, import_records, load_records
from meshseg.tracking import Tracker

SYNTH = REPO / "experiments/synthetic.yaml"


def tracker(store: Path) -> Tracker:
    return Tracker(f"sqlite:///{store}/mlflow.db", "meshseg", str(store / "artifacts"))


@pytest.fixture(scope="module")
def exported(smoke_store, tmp_path_factory):
    out, scratch = tmp_path_factory.mktemp("results"), tmp_path_factory.mktemp("tempdir")
    with pytest.MonkeyPatch.context() as m:  # every temporary folder the export makes lands in `scratch`
        m.setattr(tempfile, "tempdir", str(scratch))
        written, unchanged = export(tracker(smoke_store), out)
    return out, written, unchanged, scratch


def table_files(store: Path, out: Path, cache_dir: Path, monkeypatch) -> dict[str, bytes]:
    for k, v in smoke_env(store.parent, cache_dir).items():
        monkeypatch.setenv(k, v)
    report(SYNTH, [*SMOKE, f"report.out_dir={out}", "report.log=false"])
    return {p.name: p.read_bytes() for p in sorted((out / "synthetic").iterdir())}


def test_export_writes_one_small_record_per_finished_run(exported, smoke_store):
    out, written, unchanged, scratch = exported
    assert list(scratch.iterdir()) == []  # no temporary folder left behind (MLflow's downloads were 2 a run)
    records = load_records(out)
    assert written == len(records) == 18 and unchanged == 0  # experiments/synthetic.yaml: 3 x 3 sets x 2 folds
    path, r = records[0]
    assert path == out / r["tags"]["dataset"] / r["tags"]["category"] / f"{r['config_hash']}.json"
    assert {row["mesh"] for row in r["per_mesh"]} == set(json.loads(r["tags"]["fold_ids"])["test"])
    assert {"test/acc", "test/acc_raw", "time/train_s"} <= set(r["metrics"])
    assert r["counts"]["n_epochs"] == (1 if r["tags"]["model"] == "rf" else 2) and r["counts"]["n_test_faces"] == sum(
        row["faces"] for row in r["per_mesh"]
    )
    assert "cores" in r["tags"]["machine"] and "torch" in r["tags"]["versions"]
    assert f"lightgbm {version('lightgbm')}" in r["tags"]["versions"]  # GBDT records name their library
    assert torch.backends.cpu.get_cpu_capability() in r["tags"]["machine"]
    assert "split.k=2" in json.loads(r["tags"]["overrides"])
    assert max(p.stat().st_size for p, _ in records) < 20_000  # labels, no probabilities
    store = tracker(smoke_store)
    for _, rec in records[:3]:  # each test mesh's refined labels, bit for bit those of the store's run
        run = store.finished(rec["config_hash"])
        arrays = np.load(store.client.download_artifacts(run.info.run_id, "predictions.npz", str(scratch)))
        assert set(rec["labels"]["meshes"]) == {row["mesh"] for row in rec["per_mesh"]}
        assert rec["labels"]["classes"] == arrays[f"probs_{rec['per_mesh'][0]['mesh']}"].shape[1]
        for mesh, text in rec["labels"]["meshes"].items():
            assert np.array_equal(decode_labels(text), arrays[f"labels_{mesh}"])
    shutil.rmtree(scratch)
    scratch.mkdir()
    assert export(tracker(smoke_store), out) == (0, 18)  # exporting again changes no file


def test_import_then_report_is_byte_identical_and_import_is_idempotent(
    exported, smoke_store, tmp_path, cache_dir, monkeypatch
):
    out, *_ = exported
    empty = tmp_path / "imported/mlruns"
    first = import_records(tracker(empty), out)
    assert (len(first.imported), len(first.present), first.refused) == (18, 0, [])
    again = import_records(tracker(empty), out)
    assert (len(again.imported), len(again.present)) == (0, 18)
    assert len(tracker(empty).runs()) == 18  # importing twice added no run
    original = table_files(smoke_store, tmp_path / "a", cache_dir, monkeypatch)
    rebuilt = table_files(empty, tmp_path / "b", cache_dir, monkeypatch)
    assert set(original) >= {"table.md", "table.csv", "table.tex", "table.html"}
    for name in ("table.md", "table.csv", "table.tex", "table.html"):
        assert rebuilt[name] == original[name], name


def test_a_report_imports_only_the_records_of_the_fold_runs_its_table_wants(exported, tmp_path, cache_dir, monkeypatch):
    """A fresh clone's report of one study imported every record of the dataset (4,858 for the L-PSB, minutes)
    before its table; it imports those of its own fold runs: here rf on Cup, 2 of the 18."""
    out, *_ = exported
    for k, v in smoke_env(tmp_path, cache_dir).items():
        monkeypatch.setenv(k, v)
    args = [*SMOKE, f"report.results={out}", f"report.out_dir={tmp_path}", "report.log=false"]
    table, *_ = report(SYNTH, [*args, "report.columns=[rf]", "report.sets=[Cup]"])
    runs = tracker(tmp_path / "mlruns").runs()
    assert sorted((r.data.tags["model"], r.data.tags["category"], r.data.tags["fold"]) for r in runs) == [
        ("rf", "cup", "0"),
        ("rf", "cup", "1"),
    ]
    assert [c.status for r in table.rows for c in r.cells] == ["ok"]
    report(SYNTH, args)  # the whole table: the other 16, and nothing twice
    assert len(tracker(tmp_path / "mlruns").runs()) == 18
    bad = tmp_path / "with_bad" / "synthetic" / "cup"
    shutil.copytree(out, tmp_path / "with_bad", dirs_exist_ok=True)
    (bad / "bad.json").write_text("{not json")  # not a wanted run's, nor any run's: still named
    rep = import_records(tracker(tmp_path / "other"), tmp_path / "with_bad", hashes={runs[0].data.tags["config_hash"]})
    assert len(rep.imported) == 1 and [p.name for p, _ in rep.refused] == ["bad.json"]


def test_a_stale_record_is_refused_with_its_reason(exported, tmp_path):
    out, *_ = exported
    copy = tmp_path / "results"
    shutil.copytree(out, copy)
    path, record = load_records(copy)[0]
    record["tags"]["overrides"] = json.dumps([*json.loads(record["tags"]["overrides"]), "refine.lam=3.0"])
    path.write_text(json.dumps(record))  # as if the run had been made with another lambda than its hash says
    rep = import_records(tracker(tmp_path / "store"), copy)
    assert len(rep.imported) == 17 and [p for p, _ in rep.refused] == [path]
    assert f"config hash {record['config_hash']} is stale: today it is " in rep.refused[0][1]


def test_a_file_that_is_not_a_record_is_named(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x/bad.json").write_text("{not json")
    with pytest.raises(ValueError, match=r"x/bad.json: not a results record"):
        load_records(tmp_path)


def test_every_shipped_record_matches_todays_code():
    """results/ ships with the code: a change to run identity must re-run its records (docs/changelog.md),
    never leave them to be refused by the next import. Each record's config hash, recomputed today."""
    from hydra import initialize_config_dir

    from meshseg import CONF_DIR
    from meshseg.results import current_hash

    records = load_records(REPO / "results")
    assert len(records) >= 38  # Table 4's PSB block at least
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        stale = [str(p.relative_to(REPO)) for p, r in records if current_hash(r) != r["config_hash"]]
    assert stale == []


def test_every_shipped_cell_is_the_mean_of_its_records_per_mesh_accuracies():
    """Each complete set cell of each committed reports/<study>/table.csv, recomputed without the report
    code: the mean over the test meshes of the per-mesh accuracies its records in results/ hold. A column at
    several training seeds (issue 51) holds each test mesh once per seed: the mean over seeds of the seeds'
    means is then the mean over all its records' meshes."""
    import csv

    import numpy as np

    by_hash = {p.stem: r for p, r in load_records(REPO / "results")}
    checked = 0
    for table in sorted((REPO / "reports").glob("*/table.csv")):
        for cell in csv.DictReader(table.open()):
            if cell["kind"] != "set" or cell["status"] != "ok" or not cell["config_hashes"]:
                continue  # incomplete, n/a, or scored from released labellings (Kalogerakis 2010)
            per_mesh = [m for h in cell["config_hashes"].split() for m in by_hash[h]["per_mesh"]]
            meshes = [m["acc"] for m in per_mesh]
            seeds = len((cell.get("seeds") or "0").split())
            where = (table.parent.name, cell["row"], cell["column"])
            assert int(cell["n_meshes"]) == len({m["mesh"] for m in per_mesh}), where
            assert int(cell["n_meshes"]) * seeds == len(meshes), where
            assert float(cell["reproduced"]) == pytest.approx(100 * np.mean(meshes), abs=5e-5), where
            checked += 1
    assert checked >= 185  # Table 1's 1D CNN sets, Table 2's three columns, Table 4's block, the budget study


# Import validation, concurrency and export paths (issue 26)


def one_record_folder(exported, tmp_path, edit) -> tuple[Path, Path, dict]:
    """A results folder holding one exported record, changed by `edit(record)`."""
    out, *_ = exported
    path, record = load_records(out)[0]
    edit(record)
    copy = tmp_path / "one" / path.relative_to(out)
    copy.parent.mkdir(parents=True)
    copy.write_text(json.dumps(record))
    return tmp_path / "one", copy, record


def test_a_record_whose_tag_hash_differs_from_its_checked_hash_is_refused(exported, tmp_path):
    """Defect 1: the record's top-level hash was checked and its tags' hash stored, so a table fold's record
    carrying figure fold 0's hash in its tags made `meshseg.run category=figure fold=0` skip."""
    out, *_ = exported
    records = load_records(out)
    other = next(r for _, r in records if r["tags"]["category"] != records[0][1]["tags"]["category"])
    folder, _, record = one_record_folder(
        exported, tmp_path, lambda r: r["tags"].update(config_hash=other["config_hash"])
    )
    store = tracker(tmp_path / "store")
    rep = import_records(store, folder)
    assert rep.imported == [] and len(rep.refused) == 1
    assert f"its tags name config hash {other['config_hash']}, the record {record['config_hash']}" in rep.refused[0][1]
    assert store.finished(other["config_hash"]) is None and store.runs() == []  # that fold still trains


def test_records_that_are_not_whole_are_refused_before_any_run_is_made(exported, tmp_path):
    """Defect 4: a string metric, a record without tags.category, per-mesh rows without acc or faces,
    and category/fold in the config unlike the tags: one reason each, no run left in the store."""
    cases = {
        "metric": (lambda r: r["metrics"].update({"test/acc": "high"}), "metrics must map names to finite numbers"),
        "category": (lambda r: r["tags"].pop("category"), "tags lack ['category']"),
        "acc": (lambda r: [row.pop("acc") for row in r["per_mesh"]], "['acc'] missing or not numbers"),
        "faces": (lambda r: r["per_mesh"][0].pop("faces"), "['faces'] missing or not numbers"),
        "fold": (lambda r: r["config"].update(fold=9), "differs from its tags"),
    }
    for name, (edit, message) in cases.items():
        folder, _, _ = one_record_folder(exported, tmp_path / name, edit)
        store = tracker(tmp_path / name / "store")
        rep = import_records(store, folder)
        assert rep.imported == [] and len(rep.refused) == 1 and message in rep.refused[0][1], (name, rep.refused)
        assert store.client.search_runs([store.experiment_id], run_view_type=3) == [], name  # deleted ones too


def test_a_record_name_that_would_leave_results_is_refused_on_import_and_export(exported, tmp_path):
    """Defect 2: `category: ../../../../escape_cat` with its hash recomputed by meshseg imported, and export
    wrote four levels above `out`."""
    from meshseg.errors import ConfigError
    from meshseg.results import record_path

    folder, _, record = one_record_folder(
        exported,
        tmp_path,
        lambda r: (
            r["tags"].update(category="../../../../escape_cat"),
            r["config"].update(category="../../../../escape_cat"),
        ),
    )
    rep = import_records(tracker(tmp_path / "store"), folder)
    assert rep.imported == [] and "tags.category '../../../../escape_cat' is not a plain name" in rep.refused[0][1]
    out = tmp_path / "a/b/c/d/results"
    with pytest.raises(ConfigError, match="must be plain names"):
        record_path(out, record)
    assert not (tmp_path / "escape_cat").exists()


def _import_each(stores: list[str], folder: str, barrier, results) -> None:
    """One of two importers: `folder` into each store in turn, each import started with the other's."""
    try:
        for store in stores:
            barrier.wait(timeout=600)
            rep = import_records(tracker(Path(store)), Path(folder))
            results.put((store, len(rep.imported)))
    except BaseException as e:
        barrier.abort()  # the other importer stops waiting
        results.put(("error", repr(e)))
        raise


@pytest.mark.processes
def test_two_imports_at_once_make_one_finished_run_per_config(exported, tmp_path):
    """Defect 3: two imports of one folder into one new store at once made duplicates in 4 of 4 trials.
    Two processes import into 5 new stores in turn, both starting each import together (a barrier)."""
    import multiprocessing as mp

    out, written, *_ = exported
    stores = [str(tmp_path / f"store{trial}") for trial in range(5)]
    for store in stores:
        tracker(Path(store))  # the store exists before the race, as after a first report or sweep
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(2), ctx.Queue()
    procs = [ctx.Process(target=_import_each, args=(stores, str(out), barrier, results)) for _ in range(2)]
    for p in procs:
        p.start()
    counts = []
    while len(counts) < 2 * len(stores):
        store, got = results.get(timeout=900)
        assert store != "error", got
        counts.append((store, got))
    for p in procs:
        p.join(timeout=60)
    assert [p.exitcode for p in procs] == [0, 0]
    for trial, store in enumerate(stores):
        imported = [n for s, n in counts if s == store]
        finished = tracker(Path(store)).runs("attributes.status = 'FINISHED'")
        hashes = [r.data.tags["config_hash"] for r in finished]
        assert len(hashes) == len(set(hashes)) == written, (trial, imported)
        assert len(imported) == 2 and sum(imported) == written  # each record imported by exactly one of the two
        running = tracker(Path(store)).client.search_runs(
            [tracker(Path(store)).experiment_id], "attributes.status = 'RUNNING'", run_view_type=3
        )
        assert running == []  # claims that stepped back ended KILLED (defect 8), none left RUNNING


def test_an_import_beside_a_live_fold_run_leaves_the_fold_its_config(exported, tmp_path):
    """Defect 3: an import during a sweep of the same configs ended the fold the sweep held FINISHED twice."""
    out, written, *_ = exported
    _, record = load_records(out)[0]
    store = tracker(tmp_path / "store")
    held, _ = store.claim("a sweep's fold", {"config_hash": record["config_hash"]})  # live lease, this process
    rep = import_records(store, out)
    assert len(rep.imported) == written - 1 and len(rep.present) == 1
    runs = store.runs(f"tags.config_hash = '{record['config_hash']}'")
    assert [r.info.run_id for r in runs] == [held] and runs[0].info.status == "RUNNING"
