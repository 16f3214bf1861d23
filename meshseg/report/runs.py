"""The runs of a store as data: the FINISHED fold runs a table asks for, one row per (run, test mesh).

A table finds its runs by the config hash `meshseg.run` gives them (the newest FINISHED run of a hash wins),
so only runs made with exactly a cell's configuration (budget included) count. Each run's per-mesh table
(FoldRecord.PER_MESH) gives the rows; the run's wall time and counts ride along on each of them. The same
frame can be read from shipped results records (`results/`, meshseg.results) without a store."""

from __future__ import annotations

import logging
import tempfile
from contextlib import contextmanager
from pathlib import Path

import pandas as pd

from meshseg.errors import TrackingError
from meshseg.tracking import FoldRecord, search_runs, store_uri

log = logging.getLogger(__name__)

#: count params (`n_*`) of a fold run that learning curves read (n_train_distinct: only runs made since it exists)
RUN_COUNTS = ("n_train_samples", "n_train_distinct", "n_epochs")
#: what a run adds to each of its test meshes' rows (with `line`, the mesh's place in the run's table)
RUN_COLUMNS = ("config_hash", "run_id", "seconds", "counts", "line", "mesh", *FoldRecord.MESH_METRICS)


#: (uri, experiment) -> finished_by_hash's answer, while one_search_per_store holds
_searched: dict[tuple[str, str], dict[str, object]] | None = None


@contextmanager
def one_search_per_store():
    """Within it, each store's finished runs are searched once, however many tables read them: for a reader
    of several tables from a store nothing writes to meanwhile (the claims report; a search of a store of a
    few thousand runs takes tens of seconds)."""
    global _searched
    outer, _searched = _searched, {} if _searched is None else _searched
    try:
        yield
    finally:
        _searched = outer


def finished_by_hash(uri: str, experiment: str) -> dict[str, object]:
    """The FINISHED runs of the store by config hash, the newest of each."""
    if _searched is not None:
        key = (uri, experiment)
        if key not in _searched:
            _searched[key] = _search_finished(uri, experiment)
        return _searched[key]
    return _search_finished(uri, experiment)


def _search_finished(uri: str, experiment: str) -> dict[str, object]:
    by_hash: dict[str, object] = {}
    for r in search_runs(uri, experiment, "attributes.status = 'FINISHED'"):
        h = r.data.tags.get("config_hash")
        if h and (h not in by_hash or r.info.end_time > by_hash[h].info.end_time):
            by_hash[h] = r
    return by_hash


def _mesh_accuracies(client, run) -> list[tuple[str, dict[str, float]]]:
    """(mesh id, {metric: accuracy in %} for every FoldRecord.MESH_METRICS) of each test mesh of the run,
    from its per-mesh table (FoldRecord.PER_MESH)."""
    try:
        with tempfile.TemporaryDirectory() as tmp:
            rows = FoldRecord.read_per_mesh(_artifact(client, run, FoldRecord.PER_MESH, tmp))
            return [(row["mesh"], _percent(row)) for row in rows]
    except Exception as e:  # a FINISHED run without a readable table is damage in the store, not a missing fold
        raise TrackingError(
            f"run {run.info.run_id} ({run.info.run_name}): cannot read {'/'.join(FoldRecord.MESH_METRICS)} from "
            f"{FoldRecord.PER_MESH}: {type(e).__name__}: {e}"
        ) from None


def _artifact(client, run, name: str, tmp: str) -> str:
    """A local path to the run's artifact `name`: the file itself where the store keeps artifacts on this
    machine (a download copies it, ~50 ms a run: over a minute for a leave-one-out table), else a download."""
    from urllib.parse import urlparse

    from mlflow.utils.file_utils import local_file_uri_to_path

    uri = run.info.artifact_uri
    if urlparse(uri).scheme in ("file", ""):  # not a server's (mlflow-artifacts:, http:, s3:, ...)
        path = Path(local_file_uri_to_path(uri)) / name
        if path.is_file():
            return str(path)
    return client.download_artifacts(run.info.run_id, name, tmp)


def _run_rows(client, run) -> list[dict]:
    """One row per test mesh of the run: its accuracies, the run's identity, wall time and counts."""
    info = run.info
    common = _run_columns(run.data.tags["config_hash"], info.run_id, info.start_time, info.end_time, run.data.params)
    return [{**common, "line": i, "mesh": m, **accs} for i, (m, accs) in enumerate(_mesh_accuracies(client, run))]


def _run_columns(config_hash: str, run_id: str, start: int, end: int | None, counts: dict) -> dict:
    """What a run adds to each of its meshes' rows: identity, wall time (s; NaN while it has no end), RUN_COUNTS."""
    seconds = (end - start) / 1000 if end else float("nan")
    kept = {k: int(counts[k]) for k in RUN_COUNTS if k in counts}
    return {"config_hash": config_hash, "run_id": run_id, "seconds": seconds, "counts": kept}


def _percent(row: dict) -> dict[str, float]:
    """A per-mesh row's FoldRecord.MESH_METRICS (fractions) in %."""
    return {m: 100.0 * float(row[m]) for m in FoldRecord.MESH_METRICS}


def mesh_table(uri: str, experiment: str, wanted: pd.DataFrame) -> pd.DataFrame:
    """The fold runs `wanted` names (one row per fold run of a cell: its config_hash and the cell's keys, in
    table order) that the store at `uri` has FINISHED, one row per (wanted fold run, test mesh) with RUN_COLUMNS
    added; a fold without a run has no row. Each run's per-mesh table is read once."""
    from mlflow import MlflowClient

    by_hash = finished_by_hash(uri, experiment)
    found = [by_hash[h] for h in dict.fromkeys(wanted["config_hash"]) if h in by_hash]
    client = MlflowClient(tracking_uri=store_uri(uri)) if found else None
    return _in_order(wanted, [row for run in found for row in _run_rows(client, run)])


def records_mesh_table(root, wanted: pd.DataFrame) -> pd.DataFrame:
    """mesh_table's frame, read from the results records under `root` (e.g. results/) instead of a store: a
    record is its run exported under the run's config hash, so the wanted runs are found without importing
    the records into MLflow first (a second, where an import takes minutes). A record that `meshseg.results
    import` would refuse is no run, with a warning, as it is in the report: one that is not whole, and two
    records of one config hash (both: which of them is the run is not for the report to guess)."""
    from meshseg.results import check_record, load_records, same_hash

    hashes = set(wanted["config_hash"])
    records = [(path, record) for path, record in load_records(Path(root)) if record["config_hash"] in hashes]
    refused = same_hash(records)
    by_hash: dict[str, dict] = {}
    for path, record in records:
        why = refused.get(path) or check_record(record)
        if why is not None:
            log.warning("not read: %s: %s", path, why)
        else:
            by_hash[record["config_hash"]] = {**record, "path": str(path)}
    return _in_order(wanted, [row for record in by_hash.values() for row in _record_rows(record)])


def _record_rows(record: dict) -> list[dict]:
    """_run_rows of a record (its file's path stands for the run id, which a record does not carry)."""
    r = record
    common = _run_columns(r["config_hash"], r["path"], r["start_time"], r["end_time"], r.get("counts", {}))
    return [{**common, "line": i, "mesh": row["mesh"], **_percent(row)} for i, row in enumerate(r["per_mesh"])]


def _in_order(wanted: pd.DataFrame, rows: list[dict]) -> pd.DataFrame:
    """The runs' rows joined to the wanted fold runs they are, in `wanted`'s order, then each run's mesh order."""
    runs = pd.DataFrame(rows, columns=list(RUN_COLUMNS))
    order = wanted.assign(order=range(len(wanted)))
    meshes = order.merge(runs, on="config_hash", how="inner")
    return meshes.sort_values(["order", "line"], kind="stable").drop(columns=["order", "line"]).reset_index(drop=True)


def run_predictions(client, run_id) -> dict | None:
    """A run's per-face arrays (FoldRecord.PREDICTIONS: labels_<mesh>, ...), or None where it has none (a run
    imported from a results record without labels; a record's own path, which stands for its run id)."""
    import numpy as np
    from mlflow.exceptions import MlflowException

    if not isinstance(run_id, str) or "/" in run_id:
        return None
    try:
        with tempfile.TemporaryDirectory() as tmp:
            with np.load(client.download_artifacts(run_id, FoldRecord.PREDICTIONS, tmp)) as z:
                return {k: z[k] for k in z.files}
    except (MlflowException, OSError):  # no such artifact
        return None
