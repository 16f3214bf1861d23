"""Portable results: every FINISHED fold run of a store as one small JSON record under `results/`, and back.

    python -m meshseg.results export [tracking.uri=...] [out=results]
    python -m meshseg.results import [dir=results] [tracking.uri=...]
    python -m meshseg.results verify [dir=results] [where=TAG=VALUE,...] [n=N] [seed=0] [tol=0.005] [attach=false]
                                     [add=false] [scratch=PATH] [out=reports/verify]

MLflow is the system of record while running; `results/` is the one that ships (DESIGN "Tracking
contract"). A record holds what the report and `reproduce` need: the run's tags (config hash, fold, data
hash, ...), its resolved config, its metrics, the per-mesh table and provenance (git sha, package
versions, machine, times, the Hydra overrides it was launched with and the fold's mesh ids), and, where the
run logged them, its test meshes' refined per-face labels (`labels`, LABELS_ENCODING); probabilities stay in
the store.

Import recreates each record as a FINISHED run with the same tags, params, metrics, `config.yaml` and
`per_mesh.csv`, so the report, `reproduce` (which then skips it), the UI and the notebooks see it. It is idempotent,
also beside another import or a sweep (each run is claimed like a fold's); a record that gained labels since its run
was imported (`verify attach=true`) gives them to that run if it has none, and an export from a run without labels
keeps those its record already has (the same run: the same per-mesh accuracies). Each record is checked whole before
its run is made, and a record whose config hash the current code would no longer give to its overrides and fold (the
config changed since) is reported and skipped, never mixed in. A record is refused, with one line naming its file
and why, when it is not whole (accuracies outside [0, 1], per-mesh rows that are not its fold's test meshes, a
`test/acc` that is not their mean, a tag over MLflow's limit, ...), when its file is over MAX_RECORD_BYTES, cannot
be read or is a symbolic link (as is a linked folder), or when another record of the import has its config hash
(both); the other records are imported all the same. The import exits non-zero when it refused any record. SIGTERM
or Ctrl-C ends it with one `error:` line, the record under way removed again: no run is left RUNNING.
"""

from __future__ import annotations

import functools
import json
import logging
import math
import os
import re
import stat
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import OmegaConf

from meshseg.cli import ERROR_EXIT, command, fail, usage
from meshseg.config import hydra_scope, run_config
from meshseg.data.io import check_output_folder
from meshseg.errors import ConfigError
from meshseg.tracking import FoldRecord, RunKey, Tracker, check_store_exists, fold_identity, whole_call

log = logging.getLogger(__name__)

FORMAT = 1
#: tags that describe the tracking machinery of one store, not the run: not exported
_LOCAL_TAGS = ("lease.", "mlflow.", "superseded_by", "imported_from")


def _portable(tags: dict) -> dict:
    return {k: v for k, v in sorted(tags.items()) if not k.startswith(_LOCAL_TAGS)}


def run_name(tags: dict) -> str:
    """A fold run's name by today's format (records made before it carry an earlier one)."""
    return RunKey.from_tags(tags).name


def record_of(tracker: Tracker, run) -> dict:
    """One FINISHED fold run as a record (plain JSON types)."""
    import yaml

    run_id = run.info.run_id
    metrics = run.data.metrics
    counts = {k: int(v) for k, v in run.data.params.items() if k.startswith("n_")}
    # a download without a destination is a new temporary folder MLflow never removes: two per run per export
    with tempfile.TemporaryDirectory(prefix="meshseg-export-") as tmp:
        config = yaml.safe_load(Path(tracker.client.download_artifacts(run_id, FoldRecord.CONFIG, tmp)).read_text())
        rows = FoldRecord.read_per_mesh(tracker.client.download_artifacts(run_id, FoldRecord.PER_MESH, tmp))
        labels = _run_labels(tracker, run_id, [row["mesh"] for row in rows], tmp)
    return {
        "format": FORMAT,
        "config_hash": run.data.tags["config_hash"],
        "name": run_name(run.data.tags),
        "tags": _portable(run.data.tags),
        "config": config,
        "metrics": dict(sorted(metrics.items())),
        "counts": dict(sorted(counts.items())),
        "per_mesh": rows,
        **({"labels": labels} if labels else {}),
        "start_time": run.info.start_time,
        "end_time": run.info.end_time,
    }


#: how a record's per-face labels are written: uint8 values, zlib level 9, then base85 text. On the L-PSB (20,444
#: faces a mesh on average) the ground truth's labels take 1,917 bytes a mesh (median 810; Armadillo's and Bust's
#: face orders make them the largest, up to 17 kB), the first runs' labels 2,021 (RF) and 2,248 (1D CNN)
LABELS_ENCODING = "u8-zlib-b85"


def encode_labels(labels) -> str:
    import base64
    import zlib

    import numpy as np

    return base64.b85encode(zlib.compress(np.asarray(labels).astype(np.uint8).tobytes(), 9)).decode("ascii")


def decode_labels(text: str, limit: int | None = None):
    """The uint8 array an encode_labels text holds (ValueError or zlib.error when it holds none); with `limit`,
    at most limit + 1 labels are unpacked (a few bytes of text can inflate to gigabytes)."""
    import base64
    import zlib

    import numpy as np

    raw = base64.b85decode(text.encode("ascii"))
    data = zlib.decompress(raw) if limit is None else zlib.decompressobj().decompress(raw, limit + 1)
    return np.frombuffer(data, dtype=np.uint8)


def _run_labels(tracker: Tracker, run_id: str, meshes: list[str], tmp: str) -> dict | None:
    """The record's `labels` from the run's per-face predictions, or None (a run without them: an imported one
    made before records carried labels)."""
    import numpy as np

    if FoldRecord.PREDICTIONS not in {a.path for a in tracker.client.list_artifacts(run_id)}:
        return None
    with np.load(tracker.client.download_artifacts(run_id, FoldRecord.PREDICTIONS, tmp)) as z:
        if not all(f"labels_{m}" in z.files for m in meshes):
            return None
        probs = [f"probs_{m}" for m in meshes if f"probs_{m}" in z.files]
        if "classes" in z.files:  # a run imported from a record
            classes = int(z["classes"])
        elif probs:
            classes = int(z[probs[0]].shape[1])
        else:
            classes = int(max(z[f"labels_{m}"].max() for m in meshes)) + 1
        if not 1 <= classes <= 256 or any(z[f"labels_{m}"].min(initial=0) < 0 for m in meshes):
            return None  # not uint8 class indices: the record goes without labels rather than with wrong ones
        return {
            "encoding": LABELS_ENCODING,
            "classes": classes,
            "meshes": {m: encode_labels(z[f"labels_{m}"]) for m in meshes},
        }


#: what a dataset, category or config hash may be called where it names a folder or file under results/
_PLAIN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*")
#: the tags a record must carry: the run's identity (what its config hash was computed from), its place and its name
REQUIRED_TAGS = (
    *("config_hash", "dataset", "category", "fold", "data_hash", "overrides", "fold_ids", "model"),
    *("branches", "features", "split", "refine", "budget"),
)
#: a record is a few kB, up to ~60 kB with the labels of four large meshes (results/ holds none over 61 kB on
#: 2026-12-02): a file over this is refused unread
MAX_RECORD_BYTES = 1_000_000
#: how far `test/acc` (`test/acc_raw`) may lie from the mean of the per-mesh rows' accuracies: float rounding
#: (run.py logs np.mean of the very rows the record holds; results/ differs by 1.1e-16 at most)
MEAN_TOLERANCE = 1e-9


def plain_name(value) -> bool:
    """A single path component that stays where it is put: no separator, no `..`, no leading dot."""
    return isinstance(value, str) and _PLAIN.fullmatch(value) is not None and ".." not in value


def record_path(root: Path, record: dict) -> Path:
    """results/<dataset>/<category>/<config hash>.json, refused unless it stays under `root`."""
    t = record["tags"]
    parts = (t.get("dataset"), t.get("category"), record.get("config_hash"))
    if not all(plain_name(x) for x in parts):
        raise ConfigError(f"record {parts!r}: dataset, category and config hash must be plain names")
    path = root / parts[0] / parts[1] / f"{parts[2]}.json"
    if not path.resolve().is_relative_to(root.resolve()):
        raise ConfigError(f"record {parts!r}: {path} is outside {root}")
    return path


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def check_record(record: dict) -> str | None:
    """Why a record cannot be imported as it is, or None: every part checked before any run is created."""
    problems = (_identity_problem, _config_problem, _numbers_problem, _per_mesh_problem, _means_problem, _times_problem)
    problems += (_labels_problem,)
    for problem in problems:
        why = problem(record)
        if why is not None:
            return why
    return None


def _identity_problem(record: dict) -> str | None:
    """The config hash and the tags that name the run and its place."""
    tags, chash = record.get("tags"), record.get("config_hash")
    if not isinstance(chash, str) or not re.fullmatch(r"[0-9a-f]{16}", chash):
        return f"config_hash {chash!r} is not 16 hex digits"
    if not isinstance(tags, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in tags.items()):
        return "tags must map names to strings"
    lacking = [k for k in REQUIRED_TAGS if k not in tags]
    if lacking:
        return f"tags lack {lacking}"
    if tags["config_hash"] != chash:
        return f"its tags name config hash {tags['config_hash']}, the record {chash}"
    if why := _tag_size_problem(tags):
        return why
    bad = next((key for key in ("dataset", "category") if not plain_name(tags[key])), None)
    if bad is not None:
        return f"tags.{bad} {tags[bad]!r} is not a plain name"
    bad = next((key for key in ("fold", "branches") if not re.fullmatch(r"[0-9]+", tags[key])), None)
    if bad is not None:
        return f"tags.{bad} {tags[bad]!r} is not a whole number"
    if not _strings(_json(tags["overrides"])):
        return "tags.overrides is not a JSON list of overrides"
    if _fold_ids(tags) is None:
        return 'tags.fold_ids is not JSON {"train": [mesh ids], "test": [mesh ids]}'
    return None


def _tag_size_problem(tags: dict) -> str | None:
    """MLflow's limits on a tag (a sqlite store does not enforce them: a 50 MB tag was stored as is)."""
    from mlflow.utils.validation import MAX_ENTITY_KEY_LENGTH, MAX_TAG_VAL_LENGTH

    for key, value in tags.items():
        if len(key) > MAX_ENTITY_KEY_LENGTH:
            return f"tag name {key[:40]!r}... is {len(key)} characters, over MLflow's limit of {MAX_ENTITY_KEY_LENGTH}"
        if len(value) > MAX_TAG_VAL_LENGTH:
            return f"tags.{key[:40]} is {len(value)} characters, over MLflow's limit of {MAX_TAG_VAL_LENGTH} for a tag"
    return None


def _json(text: str):
    """`text` read as JSON, or None (deep nesting is a RecursionError, not a ValueError)."""
    try:
        return json.loads(text)
    except (ValueError, RecursionError):
        return None


def _strings(value) -> bool:
    return isinstance(value, list) and all(isinstance(x, str) for x in value)


def _fold_ids(tags: dict) -> dict | None:
    """tags.fold_ids, the fold's train and test mesh ids; None when it is not that."""
    ids = _json(tags["fold_ids"])
    ok = isinstance(ids, dict) and all(_strings(ids.get(k)) for k in ("train", "test"))
    return ids if ok else None


def _config_problem(record: dict) -> str | None:
    """The resolved config, of the category and fold its tags name."""
    tags, config = record["tags"], record.get("config")
    if not isinstance(config, dict):
        return "config is not a mapping"
    if config.get("category") != tags["category"] or str(config.get("fold")) != tags["fold"]:
        return (
            f"config (category {config.get('category')!r}, fold {config.get('fold')!r}) differs from its tags "
            f"(category {tags['category']!r}, fold {tags['fold']!r})"
        )
    return None


def _numbers_problem(record: dict) -> str | None:
    metrics, counts = record.get("metrics"), record.get("counts", {})
    if not isinstance(metrics, dict) or not all(isinstance(k, str) and _number(v) for k, v in metrics.items()):
        return "metrics must map names to finite numbers"
    if not isinstance(counts, dict) or not all(isinstance(v, int) and not isinstance(v, bool) for v in counts.values()):
        return "counts must map names to integers"
    return None


def _per_mesh_problem(record: dict) -> str | None:
    rows = record.get("per_mesh")
    if not isinstance(rows, list) or not rows:
        return "per_mesh must be a non-empty list of rows"
    for i, row in enumerate(rows):
        if not isinstance(row, dict) or not isinstance(row.get("mesh"), str):
            return f"per_mesh[{i}] has no mesh id"
        bad = [k for k in FoldRecord.PER_MESH_COLUMNS[1:] if not _number(row.get(k))]
        if bad:
            return f"per_mesh[{i}] ({row['mesh']}): {bad} missing or not numbers"
        if why := _row_problem(row):
            return f"per_mesh[{i}] ({row['mesh']}): {why}"
    # the report averages these rows: exactly the fold's test meshes, each once
    meshes, test = [row["mesh"] for row in rows], _fold_ids(record["tags"])["test"]
    if sorted(meshes) != sorted(test):
        extra, missing = sorted(set(meshes) - set(test)), sorted(set(test) - set(meshes))
        twice = sorted({m for m in meshes if meshes.count(m) > 1})
        parts = [
            *([f"not test meshes of its fold: {extra[:5]}"] if extra else []),
            *([f"missing: {missing[:5]}"] if missing else []),
            *([f"more than once: {twice[:5]}"] if twice else []),
        ]
        return f"per_mesh rows are not the fold's test meshes (tags.fold_ids): {'; '.join(parts)}"
    return None


def _labels_problem(record: dict) -> str | None:
    """Per-face labels, where a record has them: one array per test mesh, its length the mesh's faces, its values
    class indices."""
    import zlib

    labels = record.get("labels")
    if labels is None:
        return None
    if not isinstance(labels, dict) or set(labels) != {"encoding", "classes", "meshes"}:
        return "labels must hold encoding, classes and meshes"
    if labels["encoding"] != LABELS_ENCODING:
        return f"labels: encoding {labels['encoding']!r} is not {LABELS_ENCODING!r}"
    classes = labels["classes"]
    if not isinstance(classes, int) or isinstance(classes, bool) or not 1 <= classes <= 256:
        return f"labels: classes {classes!r} is not a whole number from 1 to 256"
    faces = {row["mesh"]: row["faces"] for row in record["per_mesh"]}
    if not isinstance(labels["meshes"], dict) or set(labels["meshes"]) != set(faces):
        return f"labels: meshes {sorted(labels['meshes'])[:5]} are not the per_mesh rows' {sorted(faces)[:5]}"
    for mesh, text in labels["meshes"].items():
        try:
            values = decode_labels(text, faces[mesh]) if isinstance(text, str) else None
        except (ValueError, zlib.error) as e:
            return f"labels[{mesh}]: not {LABELS_ENCODING} text ({e})"
        if values is None:
            return f"labels[{mesh}]: not {LABELS_ENCODING} text"
        if len(values) != faces[mesh]:
            count = len(values) if len(values) < faces[mesh] else f"more than {faces[mesh]}"
            return f"labels[{mesh}]: {count} labels for a mesh of {faces[mesh]} faces"
        if len(values) and int(values.max()) >= classes:
            return f"labels[{mesh}]: label {int(values.max())} is not a class index below classes={classes}"
    return None


def _row_problem(row: dict) -> str | None:
    if not isinstance(row["faces"], int) or row["faces"] < 1:
        return f"faces {row['faces']!r} is not a whole number >= 1"
    if row["area"] <= 0:
        return f"area {row['area']!r} is not > 0"
    bad = next((k for k in FoldRecord.MESH_METRICS if not 0 <= row[k] <= 1), None)
    return None if bad is None else f"{bad} {row[bad]!r} is not an accuracy in [0, 1]"


def _means_problem(record: dict) -> str | None:
    """The fold's accuracies, each the mean of its per-mesh rows' (as meshseg.run computes them)."""
    metrics, rows = record["metrics"], record["per_mesh"]
    for name, column in ((FoldRecord.ACC, "acc"), (FoldRecord.ACC_RAW, "acc_raw")):
        if name not in metrics:
            return f"metrics lack {name}"
        if not 0 <= metrics[name] <= 1:
            return f"metrics {name} {metrics[name]!r} is not an accuracy in [0, 1]"
        mean = math.fsum(row[column] for row in rows) / len(rows)
        if abs(metrics[name] - mean) > MEAN_TOLERANCE:
            return f"metrics {name} {metrics[name]!r} is not the mean of its per_mesh {column} ({mean!r})"
    return None


def _times_problem(record: dict) -> str | None:
    for key in ("start_time", "end_time"):
        if not (isinstance(record.get(key), int) or (key == "end_time" and record.get(key) is None)):
            return f"{key} {record.get(key)!r} is not a time in ms"
    return None


def write_record(path: Path, record: dict) -> bool:
    """Write atomically; False when the file already holds exactly this record."""
    text = json.dumps(record, indent=1, sort_keys=True) + "\n"
    if path.exists() and path.read_text() == text:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return True


def export(tracker: Tracker, out: Path) -> tuple[int, int]:
    """Every FINISHED fold run of the tracker's experiment into `out`: (records written, unchanged)."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # two bars per run otherwise
    written = unchanged = 0
    for run in tracker.runs("attributes.status = 'FINISHED'"):
        if "config_hash" not in run.data.tags:
            continue
        rec = record_of(tracker, run)
        try:
            path = record_path(out, rec)
        except ConfigError as e:  # a run whose names would write outside `out`: never exported
            log.warning("not exported: run %s: %s", run.info.run_id, e)
            continue
        if write_record(path, _keep_labels(path, rec)):
            written += 1
        else:
            unchanged += 1
    return written, unchanged


def _keep_labels(path: Path, rec: dict) -> dict:
    """`rec`, given the labels of the record already at `path` when its run has none but is that record's run (the
    same per-mesh accuracies): labels `verify attach=true` wrote into a record are not lost to the next export."""
    if "labels" in rec or not path.exists():
        return rec
    _, old = _read_record(path)
    if old is None or "labels" not in old or old.get("per_mesh") != rec.get("per_mesh"):
        return rec
    return {**rec, "labels": old["labels"]}


def load_records(root: Path) -> list[tuple[Path, dict]]:
    """Every record under `root`, sorted by path; a file that is not a record is one error naming it."""
    records, unread = read_records(root)
    if unread:
        path, why = unread[0]
        raise ConfigError(f"{path}: {why}")
    return records


def read_records(root: Path) -> tuple[list[tuple[Path, dict]], list[tuple[Path, str]]]:
    """The records under `root` (its `*.json` files), sorted by path, and the paths that are none, each with
    why: a file that cannot be read, is over MAX_RECORD_BYTES or is not a record, and any symbolic link,
    to a file or a folder (where it points is no part of `root`)."""
    records, unread = [], []

    def unreadable(e: OSError) -> None:  # a folder os.walk cannot list, which it would skip without a word
        unread.append((Path(e.filename), f"cannot be read ({e.strerror or e})"))

    for folder, dirs, files in os.walk(root, onerror=unreadable):  # links to folders are listed, never followed
        for name in sorted(dirs + files):
            path = Path(folder) / name
            if path.is_symlink() and (name in dirs or name.endswith(".json")):
                unread.append((path, f"a symbolic link to {os.readlink(path)}: not followed (records are plain files)"))
            elif name in files and name.endswith(".json"):
                why, record = _read_record(path)
                if why is None:
                    records.append((path, record))
                else:
                    unread.append((path, why))
    return sorted(records, key=lambda x: x[0]), sorted(unread)


def _read_record(path: Path) -> tuple[str | None, dict | None]:
    try:
        info = path.stat()
        if not stat.S_ISREG(info.st_mode):
            return "not a regular file", None
        if info.st_size > MAX_RECORD_BYTES:
            return f"{info.st_size} bytes, over the {MAX_RECORD_BYTES} a record may have: not read", None
        record = json.loads(path.read_bytes())
    except OSError as e:
        return f"cannot be read ({e.strerror or e})", None
    except (ValueError, RecursionError) as e:
        return f"not a results record ({str(e)[:200]})", None
    if not isinstance(record, dict) or record.get("format") != FORMAT or "config_hash" not in record:
        return f"not a results record of format {FORMAT}", None
    return None, record


def same_hash(records: list[tuple[Path, dict]]) -> dict[Path, str]:
    """Why each record that shares its config hash with another is refused: which is the run is unknown."""
    paths: dict[str, list[Path]] = {}
    for path, record in records:
        if isinstance(record["config_hash"], str):
            paths.setdefault(record["config_hash"], []).append(path)
    return {
        path: f"config hash {h} is also that of {', '.join(str(o) for o in same if o != path)}: both refused, keep one"
        for h, same in paths.items()
        if len(same) > 1
        for path in same
    }


#: the overrides that differ between the folds of one study
PER_FOLD = ("category", "fold")


@functools.lru_cache(maxsize=64)
def _study_config(overrides: tuple[str, ...]) -> dict:
    # resolved once for all the study's records (fold_identity copies the top level it changes; resolving took
    # a quarter of a record's import)
    return OmegaConf.to_container(run_config(overrides), resolve=True)


def current_hash(record: dict) -> str | None:
    """The config hash the code gives the record's run today: its Hydra overrides composed again with
    its category, fold and mesh ids and its data hash. None when the record does not carry them."""
    from meshseg.data.splits import Fold

    tags = record["tags"]
    if "overrides" not in tags or "fold_ids" not in tags:
        return None
    # category and fold are set on the config by fold_identity itself: the rest is what a study's records
    # share, composed once for them all (results/ composes a dozen times, not once per record)
    overrides = tuple(o for o in json.loads(tags["overrides"]) if o.lstrip("+").split("=", 1)[0] not in PER_FOLD)
    ids = json.loads(tags["fold_ids"])
    try:
        cfg = _study_config(overrides)
    except Exception as e:  # an override the code no longer knows: the config changed since
        log.debug("cannot compose %s: %s", overrides, e)
        return "(overrides no longer compose)"
    fold = Fold(int(tags["fold"]), tuple(ids["train"]), tuple(ids["test"]))
    return fold_identity(cfg, tags["category"], fold, tags["data_hash"])[1]


@dataclass
class ImportReport:
    imported: list[Path] = field(default_factory=list)
    present: list[Path] = field(default_factory=list)  # a FINISHED run of that config is in the store already
    refused: list[tuple[Path, str]] = field(default_factory=list)
    labelled: list[Path] = field(default_factory=list)  # present, and given the record's labels it lacked

    def summary(self) -> str:
        text = f"imported {len(self.imported)}, already present {len(self.present)}, refused {len(self.refused)}"
        return text + (f"; labels added to {len(self.labelled)} present runs" if self.labelled else "")


def import_records(tracker: Tracker, root: Path, hashes=None) -> ImportReport:
    """Recreate the records under `root` as FINISHED runs of the tracker's experiment (see module doc); with
    `hashes`, only the records of those config hashes (a report's fold runs: the rest are never read into the
    store), though a file that is no record, or two records of one hash, are refused all the same.
    Each record is checked whole first; its run is claimed like a fold run's (so two imports, or an import
    beside a sweep, never make two FINISHED runs of one config), and removed again if it cannot be made.
    A path under `root` that is no record is refused, the rest imported. SIGTERM and Ctrl-C end the import as
    they end a fold (KeyboardInterrupt), the record under way removed, never left RUNNING."""
    from meshseg.signals import terminate_interrupts

    with terminate_interrupts():
        return _import_records(tracker, root, hashes)


def _import_records(tracker: Tracker, root: Path, hashes) -> ImportReport:
    report = ImportReport()
    records, report.refused = read_records(root)
    shared = same_hash(records)
    if hashes is not None:  # a record whose hash is no string is kept: refused below, by name
        records = [(p, r) for p, r in records if not isinstance(r["config_hash"], str) or r["config_hash"] in hashes]
    have = tracker.finished_by_hash()  # one search, not one a record: a report's import finds most already there
    for path, record in records:
        why = shared.get(path) or check_record(record)
        if why is not None:
            report.refused.append((path, why))
            continue
        chash = record["config_hash"]
        if chash in have:
            report.present.append(path)
            if record.get("labels") and _add_labels(tracker, have[chash], record):
                report.labelled.append(path)
            continue
        now = current_hash(record)
        if now != chash:
            why = "it carries no overrides and fold ids to check it by" if now is None else f"today it is {now}"
            report.refused.append((path, f"config hash {chash} is stale: {why}"))
            continue
        tags = {**record["tags"], "config_hash": chash, "imported_from": str(path)}
        run_id = None
        try:
            with whole_call():  # an interrupt during the claim waits for the run's id, so that it is removed below
                run_id, _ = tracker.claim(run_name(record["tags"]), tags, start_time=record["start_time"])
            if run_id is None:  # another import, or a sweep, holds this config
                report.present.append(path)
                continue
            _fill(tracker, run_id, record)
        except BaseException:
            if run_id is not None:
                with whole_call():  # no half-made run stays, even if a second signal comes
                    tracker.client.set_terminated(run_id, "KILLED")
                    tracker.client.delete_run(run_id)
            raise
        have[chash] = None  # made with the record's labels, if it has them
        report.imported.append(path)
    report.refused.sort()
    return report


def _label_arrays(record: dict) -> dict | None:
    """The record's labels as FoldRecord.PREDICTIONS arrays (labels_<mesh> and classes), or None."""
    import numpy as np

    labels = record.get("labels")
    if not labels:
        return None
    arrays = {f"labels_{m}": decode_labels(t) for m, t in labels["meshes"].items()}
    arrays["classes"] = np.array(labels["classes"])
    return arrays


def _add_labels(tracker: Tracker, run, record: dict) -> bool:
    """A record that gained labels since its run was imported (e.g. by `verify attach=true`) gives them to that
    run (the store's FINISHED run of its hash; None: one this import made), which has no per-face predictions
    yet; a run with its own predictions keeps them. True if added."""
    if run is None or FoldRecord.PREDICTIONS in {a.path for a in tracker.client.list_artifacts(run.info.run_id)}:
        return False
    tracker.log_predictions(run.info.run_id, _label_arrays(record))
    return True


def _fill(tracker: Tracker, run_id: str, record: dict) -> None:
    """A claimed run made into the record's FINISHED run: params, metrics, config, per-mesh table and, where the
    record has them, the per-face labels (the predictions artifact with labels alone)."""
    from mlflow.entities import Metric, Param

    metrics, counts = record["metrics"], record.get("counts", {})
    params = {**FoldRecord.params(record["config"]), **counts}
    params = [Param(k, str(v)[:6000]) for k, v in params.items()]
    t = record["end_time"] or record["start_time"]
    metrics = [Metric(k, float(v), t, 0) for k, v in metrics.items()]
    for i in range(0, max(len(params), len(metrics)), 100):
        tracker.client.log_batch(run_id, metrics=metrics[i : i + 100], params=params[i : i + 100])
    arrays = _label_arrays(record)
    tracker.log_fold(run_id, OmegaConf.to_yaml(OmegaConf.create(record["config"])), record["per_mesh"], arrays)
    tracker.client.set_terminated(run_id, "FINISHED", end_time=record["end_time"])


@command
def main(argv=None) -> None:
    """`python -m meshseg.results export|import [key=value ...]` (tracking.* and paths.* as for meshseg.run)."""
    import sys

    argv = sys.argv[1:] if argv is None else list(argv)
    usage(__doc__.strip().split("\n\n")[1], argv)
    if argv[0] not in ("export", "import", "verify"):
        raise ConfigError(f"unknown action {argv[0]!r}: choose export, import or verify")
    action, args = argv[0], argv[1:]
    keys = ("out", "dir") + (VERIFY_KEYS if action == "verify" else ())
    own = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in args if a.split("=", 1)[0] in keys}
    overrides = [a for a in args if a.split("=", 1)[0] not in keys]
    with hydra_scope():  # once for every record's config composed again (current_hash)
        cfg = run_config(overrides)
        if action == "verify":
            return verify_main(own)
        root = Path(own.get("out", own.get("dir", "results")))
        # the paths first: a mistyped one fails before any store is opened (or created empty)
        if action == "export":
            check_output_folder(root, "out")
            check_store_exists(cfg.tracking.uri)
        elif not root.is_dir():
            raise ConfigError(f"dir={root}: no such folder of results records")
        tracker = Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir)
        if action == "export":
            written, unchanged = export(tracker, root)
            print(f"exported to {root}: {written} records written, {unchanged} unchanged")
        else:
            try:
                rep = import_records(tracker, root)
            except KeyboardInterrupt as e:  # SIGTERM or Ctrl-C: the runs made stay, the one under way is removed
                fail(f"import from {root} interrupted ({e}): no record is half-imported; run it again for the rest")
            for path, why in rep.refused:
                print(f"refused {path}: {why}", file=sys.stderr)
            print(f"import from {root} into {tracker.uri}: {rep.summary()}")
            if rep.refused:
                sys.exit(ERROR_EXIT)


VERIFY_KEYS = ("where", "n", "seed", "tol", "attach", "add", "scratch")


def _setting(own: dict, key: str, default: str, kind, low) -> float | int:
    """verify's number `key` (an int or a float >= low) from the command line."""
    text = own.get(key, default)
    try:
        value = kind(text)
    except ValueError:
        value = None
    if value is None or value < low:
        raise ConfigError(f"{key}={text} is not allowed: give {'an integer' if kind is int else 'a number'} >= {low}")
    return value


def _flag(own: dict, key: str) -> bool:
    """verify's true/false setting `key` (default false) from the command line."""
    text = own.get(key, "false").lower()
    if text not in ("true", "false"):
        raise ConfigError(f"{key}={own[key]} is not allowed: give true or false")
    return text == "true"


def attach_labels(tracker: Tracker, run, path: Path, record: dict) -> bool:
    """`verify attach=true`: the record at `path`, which has no labels, given those of `run` (its fold made again,
    agreeing with it), checked like any record and written back; False where the run has none to give."""
    with tempfile.TemporaryDirectory(prefix="meshseg-verify-") as tmp:
        labels = _run_labels(tracker, run.info.run_id, [row["mesh"] for row in record["per_mesh"]], tmp)
    if labels is None:
        return False
    labelled = {**record, "labels": labels}
    why = check_record(labelled)
    if why is not None:
        log.warning("labels not attached to %s: %s", path, why)
        return False
    write_record(path, labelled)
    record["labels"] = labels
    return True


def verify_main(own: dict) -> None:
    """`verify`: the chosen records made again and compared (meshseg.verify); its table under `out`."""
    import sys

    from meshseg import verify as V

    root = Path(own.get("dir", "results"))
    if not root.is_dir():
        raise ConfigError(f"dir={root}: no such folder of results records")
    where = V.parse_where(own.get("where"))
    n = _setting(own, "n", "", int, 1) if "n" in own else None
    seed = _setting(own, "seed", "0", int, 0)
    tol = _setting(own, "tol", str(V.TOLERANCE), float, 0.0)
    attach, add = (_flag(own, key) for key in ("attach", "add"))
    out = Path(own.get("out", "reports/verify"))
    check_output_folder(out, "out")
    kept = V.read_table(out) if add else []
    records, unreadable = read_records(root)
    for path, why in unreadable:
        print(f"refused {path}: {why}", file=sys.stderr)
    done = V.listed(kept)
    fresh = [(p, r) for p, r in records if str(p.relative_to(root)) not in done]
    chosen, choice = V.choose(fresh, where, n, seed), V.choice_text(where, n, seed)
    if kept:
        choice += f", added to the {len(kept)} records the table listed before"

    def progress(outcomes, total):  # the table rewritten after each record: a verify cut short keeps its part
        V.say(outcomes, total)
        V.write_table(out, V.table_files(kept + V.rows(outcomes, root), root, tol, choice, len(kept) + total))

    with tempfile.TemporaryDirectory(prefix="meshseg-verify-") as tmp:
        scratch = Path(own.get("scratch", tmp))
        adds = attach_labels if attach else None
        outcomes = V.verify(chosen, scratch, tol, hashes=current_hash, attach=adds, progress=progress)
    if not chosen:
        V.write_table(out, V.table_files(kept, root, tol, choice, len(kept)))
    print(f"verify: {V.summary(V.rows(outcomes, root))}; table in {out}")
    if any(o.status in ("differs", "failed") for o in outcomes):
        sys.exit(ERROR_EXIT)


if __name__ == "__main__":
    main()
