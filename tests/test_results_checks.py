"""`meshseg.results import` against records that are not what they claim (issue 48): impossible accuracies,
per-mesh rows of other meshes, oversized records and tags, two records of one config, links, unreadable
files, SIGTERM mid-import and the exit status. Records are copied from the shipped results/, no training."""

import copy
import json
import math
import os
import signal
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO
from test_results import tracker

from meshseg.results import (
    LABELS_ENCODING,
    MAX_RECORD_BYTES,
    decode_labels,
    encode_labels,
    export,
    import_records,
    main,
    record_path,
)
from meshseg.tracking import Tracker


@pytest.fixture(scope="module")
def shipped() -> list[dict]:
    """The first two 5-fold records of results/ (four test meshes each)."""
    found = []
    for path in sorted((REPO / "results").rglob("*.json")):
        record = json.loads(path.read_text())
        if record["tags"]["split"] == "5fold":
            found.append(record)
            if len(found) == 2:
                return found
    pytest.fail("results/ holds no two 5-fold records")


@pytest.fixture
def record(shipped) -> dict:
    return copy.deepcopy(shipped[0])


@pytest.fixture(scope="module")
def refusals(tmp_path_factory) -> Tracker:
    """One store for the tests whose imports must refuse everything: it stays without runs."""
    return tracker(tmp_path_factory.mktemp("refusals"))


def put(root: Path, record: dict, name: str | None = None) -> Path:
    """`record` written under `root` where export writes it (or as `name` in its folder)."""
    path = record_path(root, record)
    path = path.with_name(name) if name else path
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))
    return path


def own_lines(err: str) -> list[str]:
    """What a command wrote to stderr, MLflow's own log lines (a new store's tables) left out."""
    return [line for line in err.splitlines() if " INFO mlflow." not in line]


def every_run(store: Tracker) -> list:
    """Every run of the store, deleted ones too."""
    return store.client.search_runs([store.experiment_id], run_view_type=3)


# item 1: impossible numbers, and per-mesh rows that are not the fold's test meshes


def row_value(key, value):
    def edit(r):
        r["per_mesh"][0][key] = value
        mesh = r["per_mesh"][0]["mesh"]
        why = {
            "acc": f"acc {value!r} is not an accuracy in [0, 1]",
            "acc_raw": f"acc_raw {value!r} is not an accuracy in [0, 1]",
            "faces": f"faces {value!r} is not a whole number >= 1",
            "area": f"area {value!r} is not > 0",
        }[key]
        return f"per_mesh[0] ({mesh}): {why}"

    return edit


def percent(r):  # a record in percent: every accuracy x100
    for row in r["per_mesh"]:
        row["acc"], row["acc_raw"] = 100 * row["acc"], 100 * row["acc_raw"]
    r["metrics"]["test/acc"] *= 100
    return f"per_mesh[0] ({r['per_mesh'][0]['mesh']}): acc {r['per_mesh'][0]['acc']!r} is not an accuracy in [0, 1]"


def metric(name, value):
    def edit(r):
        r["metrics"][name] = value
        return f"metrics {name} {value!r} is not an accuracy in [0, 1]"

    return edit


def off_mean(name, column):
    def edit(r):
        mean = math.fsum(row[column] for row in r["per_mesh"]) / len(r["per_mesh"])  # as the check sums: exactly
        r["metrics"][name] = mean - 0.01 if mean > 0.5 else mean + 0.01  # a real difference, still an accuracy
        return f"metrics {name} {r['metrics'][name]!r} is not the mean of its per_mesh {column} ({mean!r})"

    return edit


def train_mesh(r):
    ids = json.loads(r["tags"]["fold_ids"])
    was, r["per_mesh"][0]["mesh"] = r["per_mesh"][0]["mesh"], ids["train"][0]
    return (
        "per_mesh rows are not the fold's test meshes (tags.fold_ids): "
        f"not test meshes of its fold: {[ids['train'][0]]}; missing: {[was]}"
    )


def twice(r):
    was, r["per_mesh"][1]["mesh"] = r["per_mesh"][1]["mesh"], r["per_mesh"][0]["mesh"]
    return (
        "per_mesh rows are not the fold's test meshes (tags.fold_ids): "
        f"missing: {[was]}; more than once: {[r['per_mesh'][0]['mesh']]}"
    )


def dropped(r):
    was = r["per_mesh"].pop()["mesh"]
    return f"per_mesh rows are not the fold's test meshes (tags.fold_ids): missing: {[was]}"


def tag(key, value, why):
    def edit(r):
        r["tags"][key] = value
        return why

    return edit


def labelled(r, classes: int = 5) -> dict:
    """The record with per-face labels for its test meshes (made up, whatever it carried): mesh i's labels
    count 0, 1, ... up to classes - 1 and round again."""
    r["labels"] = {
        "encoding": LABELS_ENCODING,
        "classes": classes,
        "meshes": {row["mesh"]: encode_labels(np.arange(row["faces"]) % classes) for row in r["per_mesh"]},
    }
    return r


def short_labels(r):
    mesh, faces = r["per_mesh"][0]["mesh"], r["per_mesh"][0]["faces"]
    labelled(r)["labels"]["meshes"][mesh] = encode_labels(np.zeros(faces - 1))
    return f"labels[{mesh}]: {faces - 1} labels for a mesh of {faces} faces"


def labels_inflating(r):  # a few kB of text that would inflate to 10 MB: unpacked only past the mesh's faces
    mesh, faces = r["per_mesh"][0]["mesh"], r["per_mesh"][0]["faces"]
    labelled(r)["labels"]["meshes"][mesh] = encode_labels(np.zeros(10_000_000))
    return f"labels[{mesh}]: more than {faces} labels for a mesh of {faces} faces"


def label_out_of_range(r):
    mesh = r["per_mesh"][1]["mesh"]
    labelled(r, classes=5)["labels"]["meshes"][mesh] = encode_labels(np.full(r["per_mesh"][1]["faces"], 5))
    return f"labels[{mesh}]: label 5 is not a class index below classes=5"


def labels_not_encoded(r):
    mesh = r["per_mesh"][0]["mesh"]
    labelled(r)["labels"]["meshes"][mesh] = "~~~ not base85 ~~~"
    try:
        decode_labels("~~~ not base85 ~~~")
    except ValueError as e:
        return f"labels[{mesh}]: not {LABELS_ENCODING} text ({e})"


def labels_of_another_mesh(r):
    labels = labelled(r)["labels"]["meshes"]
    labels["9999"] = labels.pop(r["per_mesh"][0]["mesh"])
    shown, rows = sorted(labels)[:5], sorted(row["mesh"] for row in r["per_mesh"])[:5]
    return f"labels: meshes {shown} are not the per_mesh rows' {rows}"


IMPOSSIBLE = {
    "acc 1.5": row_value("acc", 1.5),
    "acc -0.25": row_value("acc", -0.25),
    "acc_raw 1.5": row_value("acc_raw", 1.5),
    "accuracies x100": percent,
    "faces 0": row_value("faces", 0),
    "faces 2.5": row_value("faces", 2.5),
    "area 0": row_value("area", 0.0),
    "area -1": row_value("area", -1.0),
    "test/acc 7.0": metric("test/acc", 7.0),
    "test/acc_raw -0.5": metric("test/acc_raw", -0.5),
    "test/acc not the rows' mean": off_mean("test/acc", "acc"),
    "test/acc_raw not the rows' mean": off_mean("test/acc_raw", "acc_raw"),
    "test/acc missing": lambda r: (r["metrics"].pop("test/acc"), "metrics lack test/acc")[1],
    "a training mesh's row": train_mesh,
    "a mesh twice": twice,
    "a test mesh without its row": dropped,
    # what the checks above read, and the run's name: malformed, each was a traceback
    "fold_ids not JSON": tag("fold_ids", "{", 'tags.fold_ids is not JSON {"train": [mesh ids], "test": [mesh ids]}'),
    "overrides not a list": tag("overrides", '"split=5fold"', "tags.overrides is not a JSON list of overrides"),
    "branches not a number": tag("branches", "three", "tags.branches 'three' is not a whole number"),
    "split tag missing": lambda r: (r["tags"].pop("split"), "tags lack ['split']")[1],
    # per-face labels (issue 50)
    "labels one short": short_labels,
    "labels inflating to 10 MB": labels_inflating,
    "a label out of range": label_out_of_range,
    "labels not encoded": labels_not_encoded,
    "labels of another mesh": labels_of_another_mesh,
    "labels' encoding unknown": lambda r: (
        labelled(r)["labels"].update(encoding="u8-raw"),
        f"labels: encoding 'u8-raw' is not {LABELS_ENCODING!r}",
    )[1],
}


def test_the_shipped_record_itself_imports(record, tmp_path):
    """The cases below differ from it only by their edit."""
    store = tracker(tmp_path / "store")
    path = put(tmp_path / "results", record)
    rep = import_records(store, tmp_path / "results")
    assert (rep.imported, rep.refused) == ([path], [])
    assert [r.info.status for r in every_run(store)] == ["FINISHED"]


def imported_and_exported(record, tmp_path) -> tuple[Tracker, Path]:
    """A new store with `record` imported, and the path of the record its export wrote."""
    store = tracker(tmp_path / "store")
    put(tmp_path / "in", record)
    assert import_records(store, tmp_path / "in").refused == []
    assert export(store, tmp_path / "out") == (1, 0)
    [path] = (tmp_path / "out").rglob("*.json")
    return store, path


def test_labels_round_trip_through_import_and_export_bit_for_bit(record, tmp_path):
    """A record's per-face labels become the imported run's predictions artifact and come back out of export
    unchanged; a record without labels still imports (the test above) and exports without them."""
    labelled(record, classes=7)
    _, path = imported_and_exported(record, tmp_path)
    back = json.loads(path.read_text())
    assert back["labels"] == record["labels"]
    for row in record["per_mesh"]:
        assert np.array_equal(decode_labels(back["labels"]["meshes"][row["mesh"]]), np.arange(row["faces"]) % 7)


def test_an_export_from_a_run_without_labels_keeps_the_labels_its_record_has(record, tmp_path):
    """`verify attach=true` writes labels into a record whose run has none: the next export keeps them, unless the
    run is not the record's (other per-mesh accuracies), whose labels would then be another run's."""
    record.pop("labels", None)  # a record from before records carried labels
    store, path = imported_and_exported(record, tmp_path)
    bare = json.loads(path.read_text())
    assert "labels" not in bare
    attached = labelled(json.loads(path.read_text()), classes=7)
    path.write_text(json.dumps(attached))
    assert export(store, tmp_path / "out") == (1, 0)  # written again, in the writer's own layout, labels kept
    assert json.loads(path.read_text()) == attached
    assert export(store, tmp_path / "out") == (0, 1)
    attached["per_mesh"][0]["acc"] /= 2  # another run's record at this path: its labels are not this run's
    path.write_text(json.dumps(attached))
    export(store, tmp_path / "out")
    assert json.loads(path.read_text()) == bare


@pytest.mark.parametrize("case", IMPOSSIBLE)
def test_an_impossible_record_is_refused_and_nothing_imported(case, record, tmp_path, refusals):
    why = IMPOSSIBLE[case](record)
    path = put(tmp_path, record)
    rep = import_records(refusals, tmp_path)
    assert (rep.imported, rep.refused) == ([], [(path, why)])
    assert every_run(refusals) == []


# item 6: size limits, SIGTERM


def test_a_record_over_the_size_limit_is_refused_unread(record, tmp_path, refusals, monkeypatch):
    path = put(tmp_path, record)
    path.write_text(json.dumps(record) + " " * MAX_RECORD_BYTES)  # valid JSON, and a whole record
    size = path.stat().st_size
    read_bytes = Path.read_bytes
    monkeypatch.setattr(Path, "read_bytes", lambda p: pytest.fail("read") if p == path else read_bytes(p))
    rep = import_records(refusals, tmp_path)
    assert rep.refused == [(path, f"{size} bytes, over the {MAX_RECORD_BYTES} a record may have: not read")]
    assert every_run(refusals) == []


@pytest.mark.parametrize("where", ["value", "name"])
def test_a_tag_over_mlflows_limit_is_refused(where, record, tmp_path, refusals):
    if where == "value":
        record["tags"]["versions"] = "x" * 8001
        why = "tags.versions is 8001 characters, over MLflow's limit of 8000 for a tag"
    else:
        record["tags"]["k" * 251] = "v"
        why = f"tag name {'k' * 40!r}... is 251 characters, over MLflow's limit of 250"
    path = put(tmp_path, record)
    rep = import_records(refusals, tmp_path)
    assert (rep.imported, rep.refused) == ([], [(path, why)])
    assert every_run(refusals) == []


def sigterm_after(obj, name: str, monkeypatch) -> None:
    """SIGTERM to this process as soon as `obj.name` returns."""
    original = getattr(obj, name)

    def hit(*args, **kwargs):
        out = original(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)  # its handler runs on this thread at the next bytecode
        return out

    monkeypatch.setattr(obj, name, hit)


def test_sigterm_just_after_the_claim_creates_its_run_leaves_no_run_running(record, tmp_path, monkeypatch):
    """The claim's new run, its id not yet returned when SIGTERM lands: it must still end (and be removed)."""
    store = tracker(tmp_path / "store")
    put(tmp_path / "results", record)
    sigterm_after(store, "_create", monkeypatch)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM received"):
        import_records(store, tmp_path / "results")
    runs = every_run(store)
    assert len(runs) == 1 and runs[0].info.status == "KILLED" and store.runs() == []  # ended, and deleted


def test_sigterm_mid_import_is_one_error_line_and_leaves_no_run(record, tmp_path, monkeypatch, capsys):
    """SIGTERM while a record's run is being filled: the command ends with one `error:` line, exit status 1,
    and the half-made run is gone (a rerun imports the record)."""
    store = tmp_path / "store"
    tracker(store)
    put(tmp_path / "results", record)
    sigterm_after(Tracker, "log_fold", monkeypatch)
    uri = f"tracking.uri=sqlite:///{store}/mlflow.db"
    with pytest.raises(SystemExit) as end:
        main(["import", f"dir={tmp_path / 'results'}", uri, f"tracking.artifact_dir={store / 'artifacts'}"])
    assert end.value.code == 1
    assert own_lines(capsys.readouterr().err) == [
        f"error: import from {tmp_path / 'results'} interrupted (SIGTERM received): no record is half-imported; "
        "run it again for the rest"
    ]
    assert [r.info.status for r in every_run(tracker(store))] == ["KILLED"] and tracker(store).runs() == []


# item 7: two records of one config in one import


def test_two_records_of_one_config_hash_are_both_refused(record, tmp_path, refusals):
    first = put(tmp_path, record)
    record["per_mesh"][0]["acc"] = 1.0  # another accuracy under the same config hash
    second = put(tmp_path, record, "copy.json")
    chash = record["config_hash"]
    rep = import_records(refusals, tmp_path)
    assert rep.imported == [] and rep.refused == [
        (first, f"config hash {chash} is also that of {second}: both refused, keep one"),
        (second, f"config hash {chash} is also that of {first}: both refused, keep one"),
    ]
    assert every_run(refusals) == []


# item 10: the exit status, links, unreadable files


def cli_import(folder: Path, store: Path) -> int:
    uri = f"tracking.uri=sqlite:///{store}/mlflow.db"
    try:
        main(["import", f"dir={folder}", uri, f"tracking.artifact_dir={store / 'artifacts'}"])
    except SystemExit as e:
        return e.code
    return 0


def test_import_exits_non_zero_when_it_refused_a_record(shipped, tmp_path, capsys):
    good, bad = copy.deepcopy(shipped)
    bad["per_mesh"][0]["acc"] = 1.5
    put(tmp_path / "results", good)
    bad_path = put(tmp_path / "results", bad)
    assert cli_import(tmp_path / "results", tmp_path / "store") == 1
    out, err = capsys.readouterr()
    mesh = bad["per_mesh"][0]["mesh"]
    assert own_lines(err) == [f"refused {bad_path}: per_mesh[0] ({mesh}): acc 1.5 is not an accuracy in [0, 1]"]
    assert out.endswith(": imported 1, already present 0, refused 1\n")
    assert cli_import(tmp_path / "results", tmp_path / "store") == 1  # refused again, however often it runs
    bad_path.unlink()
    assert cli_import(tmp_path / "results", tmp_path / "store") == 0


def test_linked_record_files_and_folders_are_both_refused(record, shipped, tmp_path, refusals):
    outside = tmp_path / "outside"
    target = put(outside, record)
    folder = tmp_path / "results"
    (folder / "psb").mkdir(parents=True)
    file_link = folder / "psb" / "linked.json"
    file_link.symlink_to(target)
    dir_link = folder / "psb" / "Linked"
    dir_link.symlink_to(target.parent, target_is_directory=True)
    rep = import_records(refusals, folder)
    assert rep.imported == [] and rep.refused == [
        (dir_link, f"a symbolic link to {target.parent}: not followed (records are plain files)"),
        (file_link, f"a symbolic link to {target}: not followed (records are plain files)"),
    ]
    assert every_run(refusals) == []


@pytest.mark.parametrize("how", ["permission", "not UTF-8"])
def test_an_unreadable_file_is_named_and_the_rest_imported(how, shipped, tmp_path, monkeypatch):
    """One file that cannot be read no longer stops the import (nor a report's): it is refused by name."""
    good, other = copy.deepcopy(shipped)
    good_path, bad = put(tmp_path / "results", good), put(tmp_path / "results", other)
    if how == "permission":  # chmod 000 does not stop root, and the tests may run as root
        read_bytes = Path.read_bytes

        def denied(self):
            if self == bad:
                raise PermissionError(13, "Permission denied", str(self))
            return read_bytes(self)

        monkeypatch.setattr(Path, "read_bytes", denied)
        why = "cannot be read (Permission denied)"
    else:
        bad.write_bytes(b"\xff\xfe\x00garbage")
        why = None
    rep = import_records(tracker(tmp_path / "store"), tmp_path / "results")
    assert rep.imported == [good_path] and [p for p, _ in rep.refused] == [bad]
    if why is not None:
        assert rep.refused[0][1] == why
    else:
        assert rep.refused[0][1].startswith("not a results record (")
