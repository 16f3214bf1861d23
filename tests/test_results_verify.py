"""`python -m meshseg.results verify`: a shipped record made again in a scratch store and compared mesh by mesh."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import smoke_env

from meshseg.errors import ConfigError
from meshseg.results import decode_labels, export, import_records, load_records, main, write_record
from meshseg.tracking import Tracker
from meshseg.verify import choose, compare, parse_where, verify


@pytest.fixture(scope="module")
def rf_record(smoke_store, tmp_path_factory):
    """One random-forest record of the smoke store, exported alone into its own folder."""
    out = tmp_path_factory.mktemp("records")
    export(Tracker(f"sqlite:///{smoke_store}/mlflow.db", "meshseg", str(smoke_store / "artifacts")), out)
    path, record = next((p, r) for p, r in load_records(out) if r["tags"]["model"] == "rf")
    alone = tmp_path_factory.mktemp("one") / path.relative_to(out)
    write_record(alone, record)
    return alone.parents[2], record


def edited(record: dict, by: float) -> dict:
    """The record with its first mesh's accuracy moved by `by`, and test/acc its rows' mean again (a whole record)."""
    r = json.loads(json.dumps(record))
    r["per_mesh"][0]["acc"] += by
    r["metrics"]["test/acc"] = sum(row["acc"] for row in r["per_mesh"]) / len(r["per_mesh"])
    return r


def test_a_record_made_again_is_identical_and_a_hand_edited_one_differs(rf_record, tmp_path, cache_dir, monkeypatch):
    root, record = rf_record
    for k, v in smoke_env(tmp_path, cache_dir).items():
        monkeypatch.setenv(k, v)
    scratch, out = tmp_path / "scratch", tmp_path / "verify"
    main(["verify", f"dir={root}", f"scratch={scratch}", f"out={out}"])  # returns: nothing differs
    md = (out / "verify.md").read_text()
    assert "Outcome: 1 identical; largest per-mesh |Δ| 0.00e+00." in md and record["name"] in md
    assert Tracker(f"sqlite:///{scratch}/mlflow.db", "meshseg").finished(record["config_hash"])  # made again there

    copy = tmp_path / "edited"
    write_record(
        copy / "synthetic" / record["tags"]["category"] / f"{record['config_hash']}.json", edited(record, -0.2)
    )
    with pytest.raises(SystemExit) as done:  # the scratch store has the run: compared, not made again
        main(["verify", f"dir={copy}", f"scratch={scratch}", f"out={out}"])
    assert done.value.code == 1
    row = next(r for r in (out / "verify.csv").read_text().splitlines()[1:])
    assert ",differs," in row and ",2.00e-01," in row  # the edit, to the last digit shown


def test_compare_statuses():
    rows = [{"mesh": "1", "acc": 0.9, "acc_raw": 0.8}, {"mesh": "2", "acc": 0.7, "acc_raw": 0.6}]
    assert compare(rows, rows, 0.005) == ("identical", {"acc": 0.0, "acc_raw": 0.0})
    near = [dict(rows[0], acc=0.903), rows[1]]
    status, delta = compare(rows, near, 0.005)
    assert status == "within" and delta["acc"] == pytest.approx(0.003) and delta["acc_raw"] == 0
    assert compare(rows, near, 0.002)[0] == "differs"
    assert compare(rows, rows[:1], 0.005) == ("differs", {})  # not the same test meshes


def test_a_stale_record_is_reported_not_made_again(rf_record, tmp_path):
    root, record = rf_record
    [out] = verify(
        [(root / "x.json", record)],
        tmp_path / "scratch",
        hashes=lambda r: "0123456789abcdef",
        progress=lambda o, n: None,
    )
    assert (out.status, out.why, out.delta) == ("stale", "today's config hash 0123456789abcdef", {})
    assert not (tmp_path / "scratch" / "logs").exists()  # no run was launched


def fake(model, split, i):
    return Path(f"{model}-{split}-{i}.json"), {"tags": {"model": model, "split": split, "category": "Cup"}}


def test_a_sample_is_seeded_and_spread_over_methods_and_splits():
    records = [fake(m, s, i) for m in ("cnn1d", "rf") for s in ("loo", "5fold") for i in range(5)] + [
        fake("gbdt", "loo", 0)
    ]
    sample = choose(records, {}, 5, seed=3)
    assert len(sample) == 5 and len({(r["tags"]["model"], r["tags"]["split"]) for _, r in sample}) == 5
    assert sample == choose(records, {}, 5, seed=3) and sample != choose(records, {}, 5, seed=4)
    assert [p.name for p, _ in choose(records, {"model": "gbdt"}, None, 0)] == ["gbdt-loo-0.json"]
    assert parse_where("model=rf,split=loo") == {"model": ("rf",), "split": ("loo",)}
    either = parse_where("model=gbdt|cnn1d,split=loo")
    assert either == {"model": ("gbdt", "cnn1d"), "split": ("loo",)}
    assert sorted(p.name for p, _ in choose(records, either, None, 0)) == [
        *(f"cnn1d-loo-{i}.json" for i in range(5)),
        "gbdt-loo-0.json",
    ]
    with pytest.raises(ConfigError, match=r"where=model: 'model' is not tag=value"):
        parse_where("model")
    with pytest.raises(ConfigError, match=r"where=model=rf\|: 'model=rf\|' is not tag=value"):
        parse_where("model=rf|")


def test_attach_gives_a_record_without_labels_those_of_its_run_made_again_and_import_passes_them_on(
    rf_record, tmp_path, cache_dir, monkeypatch
):
    root, record = rf_record
    assert record.get("labels")  # the smoke run logged them: the reference
    for k, v in smoke_env(tmp_path, cache_dir).items():
        monkeypatch.setenv(k, v)
    bare = {k: v for k, v in record.items() if k != "labels"}
    path = tmp_path / "records" / "synthetic" / record["tags"]["category"] / f"{record['config_hash']}.json"
    write_record(path, bare)
    store = Tracker(f"sqlite:///{tmp_path}/store/mlflow.db", "meshseg", str(tmp_path / "store" / "artifacts"))
    assert len(import_records(store, tmp_path / "records").imported) == 1  # a run without per-face labels

    args = ["verify", f"dir={tmp_path / 'records'}", f"scratch={tmp_path / 'scratch'}", f"out={tmp_path / 'v'}"]
    main(args)
    assert "labels" not in json.loads(path.read_text())  # attach=false: the record is left alone
    main([*args, "attach=true"])
    labelled = json.loads(path.read_text())
    assert labelled == record  # the labels of the run made again are the exported ones, bit for bit
    assert "labels attached to 1 records" in (tmp_path / "v" / "verify.md").read_text()

    rep = import_records(store, tmp_path / "records")  # the present run gets them; a second time nothing
    assert (len(rep.imported), len(rep.present), len(rep.labelled)) == (0, 1, 1)
    assert len(import_records(store, tmp_path / "records").labelled) == 0
    run = store.finished(record["config_hash"])
    arrays = np.load(store.client.download_artifacts(run.info.run_id, "predictions.npz", str(tmp_path / "dl")))
    for mesh, text in record["labels"]["meshes"].items():
        assert np.array_equal(arrays[f"labels_{mesh}"], decode_labels(text))


def test_add_keeps_the_table_and_chooses_only_records_it_does_not_list(
    rf_record, tmp_path, cache_dir, monkeypatch, capsys
):
    import csv

    from meshseg.verify import HEADER

    root, record = rf_record
    for k, v in smoke_env(tmp_path, cache_dir).items():
        monkeypatch.setenv(k, v)
    rel = next(str(p.relative_to(root)) for p in root.rglob("*.json"))
    out, scratch = tmp_path / "verify", tmp_path / "scratch"
    elsewhere = ["psb/Cup/0123456789abcdef.json", "Cup f0", "rf", "loo", "Cup", "0", "within", "1.00e-04", "0.00e+00"]
    elsewhere += ["9", "", "Other CPU, 2 cores", "Other CPU, 2 cores", ""]
    out.mkdir()
    with (out / "verify.csv").open("w", newline="") as f:
        csv.writer(f).writerows([HEADER, elsewhere])

    args = ["verify", f"dir={root}", f"scratch={scratch}", f"out={out}", "add=true"]
    main(args)  # the rf record is not listed: made again and added below the kept row
    body = list(csv.reader((out / "verify.csv").open()))[1:]
    assert [r[0] for r in body] == ["psb/Cup/0123456789abcdef.json", rel] and body[1][6] == "identical"
    md = (out / "verify.md").read_text()
    assert "added to the 1 records the table listed before" in md
    assert "Made again on: Other CPU, 2 cores (1 records); " in md and "Outcome: 1 identical, 1 within;" in md

    before = (out / "verify.csv").read_text()
    main(args)  # both listed now: nothing chosen, nothing made, the table as it was
    assert (out / "verify.csv").read_text() == before
    assert "Outcome: 1 identical, 1 within; largest per-mesh |Δ| 1.00e-04." in (out / "verify.md").read_text()

    (out / "verify.csv").write_text(",".join(h for h in HEADER if h != "made again on") + "\n")
    with pytest.raises(SystemExit):
        main(args)
    assert "verify.csv: not a verify table of today's columns (record, run," in capsys.readouterr().err
    main(args[:-1])  # without add the old table is simply replaced
    assert list(csv.reader((out / "verify.csv").open()))[0] == list(HEADER)
