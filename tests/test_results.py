"""Portable results (`meshseg.results`): the smoke store exported to JSON records, imported into an empty store,
and the report rebuilt from the import byte for byte; import is idempotent and refuses stale records."""

import json
import shutil
from pathlib import Path

import pytest
from conftest import REPO, SMOKE, smoke_env

from meshseg.report import report
from meshseg.results import export, import_records, load_records
from meshseg.tracking import Tracker

SYNTH = REPO / "experiments/synthetic.yaml"


def tracker(store: Path) -> Tracker:
    return Tracker(f"sqlite:///{store}/mlflow.db", "meshseg", str(store / "artifacts"))


@pytest.fixture(scope="module")
def exported(smoke_store, tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    written, unchanged = export(tracker(smoke_store), out)
    return out, written, unchanged


def table_files(store: Path, out: Path, cache_dir: Path, monkeypatch) -> dict[str, bytes]:
    for k, v in smoke_env(store.parent, cache_dir).items():
        monkeypatch.setenv(k, v)
    report(SYNTH, [*SMOKE, f"report.out_dir={out}", "report.log=false"])
    return {p.name: p.read_bytes() for p in sorted((out / "synthetic").iterdir())}


def test_export_writes_one_small_record_per_finished_run(exported, smoke_store):
    out, written, unchanged = exported
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
    assert "split.k=2" in json.loads(r["tags"]["overrides"])
    assert max(p.stat().st_size for p, _ in records) < 20_000  # no per-face arrays
    assert export(tracker(smoke_store), out) == (0, 18)  # exporting again changes no file


def test_import_then_report_is_byte_identical_and_import_is_idempotent(
    exported, smoke_store, tmp_path, cache_dir, monkeypatch
):
    out, _, _ = exported
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


def test_a_stale_record_is_refused_with_its_reason(exported, tmp_path):
    out, _, _ = exported
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
