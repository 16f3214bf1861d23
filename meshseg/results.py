"""Portable results: every FINISHED fold run of a store as one small JSON record under `results/`, and back.

    python -m meshseg.results export [tracking.uri=...] [out=results]
    python -m meshseg.results import [dir=results] [tracking.uri=...]

MLflow is the system of record while running; `results/` is the one that ships (DESIGN "Tracking
contract"). A record holds what the report and `reproduce` need: the run's tags (config hash, fold, data
hash, ...), its resolved config, its metrics, the per-mesh table and provenance (git sha, package
versions, machine, times, the Hydra overrides it was launched with and the fold's mesh ids). Per-face
predictions stay in the store's artifacts.

Import recreates each record as a FINISHED run with the same tags, params, metrics, `config.yaml` and
`per_mesh.csv`, so the report, `reproduce` (which then skips it), the UI and the notebooks see it. It is
idempotent (a config hash with a FINISHED run is not imported again), and a record whose config hash the
current code would no longer give to its overrides and fold (the config changed since) is reported and
skipped, never mixed in.
"""

from __future__ import annotations

import csv
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import OmegaConf

from meshseg.errors import ConfigError, MeshsegError
from meshseg.tracking import FoldRecord, Tracker, fold_identity

log = logging.getLogger(__name__)

FORMAT = 1
#: tags that describe the tracking machinery of one store, not the run: not exported
_LOCAL_TAGS = ("lease.", "mlflow.", "superseded_by", "imported_from")


def _portable(tags: dict) -> dict:
    return {k: v for k, v in sorted(tags.items()) if not k.startswith(_LOCAL_TAGS)}


def run_name(tags: dict) -> str:
    """A fold run's name by today's format (records made before it carry an earlier one)."""
    t = tags
    return FoldRecord.name(t["category"], t["fold"], t["model"], t["branches"], t["features"], t["split"], t["budget"])


def record_of(tracker: Tracker, run) -> dict:
    """One FINISHED fold run as a record (plain JSON types)."""
    import yaml

    run_id = run.info.run_id
    metrics, counts = FoldRecord.upgrade(run.data.metrics)  # a run logged under earlier metric names too
    counts.update({k: int(v) for k, v in run.data.params.items() if k.startswith("n_")})
    config = yaml.safe_load(Path(tracker.client.download_artifacts(run_id, FoldRecord.CONFIG)).read_text())
    with open(tracker.client.download_artifacts(run_id, FoldRecord.PER_MESH), newline="") as f:
        rows = [
            {k: (v if k == "mesh" else int(v) if k == "faces" else float(v)) for k, v in row.items()}
            for row in csv.DictReader(f)
        ]
    return {
        "format": FORMAT,
        "config_hash": run.data.tags["config_hash"],
        "name": run_name(run.data.tags),
        "tags": _portable(run.data.tags),
        "config": config,
        "metrics": dict(sorted(metrics.items())),
        "counts": dict(sorted(counts.items())),
        "per_mesh": rows,
        "start_time": run.info.start_time,
        "end_time": run.info.end_time,
    }


def record_path(root: Path, record: dict) -> Path:
    t = record["tags"]
    return root / t["dataset"] / t["category"] / f"{record['config_hash']}.json"


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
        if write_record(record_path(out, rec := record_of(tracker, run)), rec):
            written += 1
        else:
            unchanged += 1
    return written, unchanged


def load_records(root: Path) -> list[tuple[Path, dict]]:
    """Every record under `root`, sorted by path; a file that is not a record is one error naming it."""
    out = []
    for path in sorted(Path(root).rglob("*.json")):
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise ConfigError(f"{path}: not a results record ({e})") from None
        if not isinstance(record, dict) or record.get("format") != FORMAT or "config_hash" not in record:
            raise ConfigError(f"{path}: not a results record of format {FORMAT}")
        out.append((path, record))
    return out


def current_hash(record: dict) -> str | None:
    """The config hash the code gives the record's run today: its Hydra overrides composed again with
    its category, fold and mesh ids and its data hash. None when the record does not carry them."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from meshseg import CONF_DIR
    from meshseg.data.splits import Fold

    tags = record["tags"]
    if "overrides" not in tags or "fold_ids" not in tags:
        return None
    overrides = json.loads(tags["overrides"])
    ids = json.loads(tags["fold_ids"])
    try:
        if GlobalHydra.instance().is_initialized():
            cfg = compose("run", overrides=overrides)
        else:
            with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
                cfg = compose("run", overrides=overrides)
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

    def summary(self) -> str:
        return f"imported {len(self.imported)}, already present {len(self.present)}, refused {len(self.refused)}"


def import_records(tracker: Tracker, root: Path) -> ImportReport:
    """Recreate the records under `root` as FINISHED runs of the tracker's experiment (see module doc)."""
    from mlflow.entities import Metric, Param

    report = ImportReport()
    have = {r.data.tags.get("config_hash") for r in tracker.runs("attributes.status = 'FINISHED'")}
    for path, record in load_records(root):
        chash = record["config_hash"]
        if chash in have:
            report.present.append(path)
            continue
        now = current_hash(record)
        if now != chash:
            why = "it carries no overrides and fold ids to check it by" if now is None else f"today it is {now}"
            report.refused.append((path, f"config hash {chash} is stale: {why}"))
            continue
        tags = {**record["tags"], "imported_from": str(path)}
        run = tracker.client.create_run(
            tracker.experiment_id, start_time=record["start_time"], tags=tags, run_name=run_name(record["tags"])
        )
        run_id = run.info.run_id
        metrics, counts = FoldRecord.upgrade(record["metrics"])  # records exported under earlier names too
        counts.update(record.get("counts", {}))
        params = {**FoldRecord.params(record["config"]), **counts}
        params = [Param(k, str(v)[:6000]) for k, v in params.items()]
        t = record["end_time"] or record["start_time"]
        metrics = [Metric(k, float(v), t, 0) for k, v in metrics.items()]
        for i in range(0, max(len(params), len(metrics)), 100):
            tracker.client.log_batch(run_id, metrics=metrics[i : i + 100], params=params[i : i + 100])
        tracker.log_fold(run_id, OmegaConf.to_yaml(OmegaConf.create(record["config"])), record["per_mesh"], None)
        tracker.client.set_terminated(run_id, "FINISHED", end_time=record["end_time"])
        have.add(chash)
        report.imported.append(path)
    return report


def main(argv=None) -> None:
    """`python -m meshseg.results export|import [key=value ...]` (tracking.* and paths.* as for meshseg.run)."""
    import sys

    from hydra import compose, initialize_config_dir

    from meshseg import CONF_DIR

    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] not in ("export", "import"):
        print(__doc__.strip().split("\n\n")[1])
        sys.exit(0 if argv and argv[0] in ("-h", "--help") else 2)
    action, args = argv[0], argv[1:]
    own = {a.split("=", 1)[0]: a.split("=", 1)[1] for a in args if a.split("=", 1)[0] in ("out", "dir")}
    overrides = [a for a in args if a.split("=", 1)[0] not in ("out", "dir")]
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            cfg = compose("run", overrides=overrides)
            tracker = Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir)
            root = Path(own.get("out", own.get("dir", "results")))
            if action == "export":
                written, unchanged = export(tracker, root)
                print(f"exported to {root}: {written} records written, {unchanged} unchanged")
            else:
                if not root.is_dir():
                    raise ConfigError(f"dir={root}: no such folder of results records")
                rep = import_records(tracker, root)
                for path, why in rep.refused:
                    print(f"refused {path}: {why}", file=sys.stderr)
                print(f"import from {root} into {tracker.uri}: {rep.summary()}")
    except MeshsegError as e:
        sys.exit(f"error: {e}")


if __name__ == "__main__":
    main()
