"""Where a column's errors lie: each test mesh's wrongly labelled area, split by how far the face is from the
nearest ground-truth part boundary in face rings (edge steps; ring 0: a face with an edge-neighbour of another
label). Errors in the first rings are a boundary placed a little off, what a boundary term (the graph cut's)
can move; errors deep inside parts are whole regions given the wrong label, which it cannot.

Opt-in (`report.boundaries=true`): it loads every test mesh and reads every run's per-face predictions from
the store (FoldRecord.PREDICTIONS). A run imported from a `results/` record has the record's refined labels
(records exported since 2026-12-02) or none (older ones: no row here, and under report.metric=acc_raw never,
records keeping no argmax); a predictions column (Kalogerakis 2010's labellings) is read from disk as the table
scores it.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pandas as pd
import scipy.sparse.csgraph as csgraph
from omegaconf import OmegaConf

from meshseg.features.geometry import face_adjacency
from meshseg.report.cells import Table

log = logging.getLogger(__name__)

#: ring bands (first, last; None: no last), and their names in the frame and the files
BANDS = ((0, 0), (1, 2), (3, 5), (6, None))
BAND_NAMES = tuple(f"{lo}" if lo == hi else f"{lo}+" if hi is None else f"{lo}-{hi}" for lo, hi in BANDS)
#: the frame's columns: the cell's keys, the mesh, its wrong area (% of its area) in all and in each band
COLUMNS = ("group", "row", "column", "mesh", "err", *(f"err_{b}" for b in BAND_NAMES))


def boundary_rings(faces: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Rings (edge steps) from each face to the nearest face that has an edge-neighbour of another label
    (0 on the boundary itself); inf on a mesh of one label, or on a part of the mesh no boundary reaches."""
    adjacency = face_adjacency(faces)
    a = adjacency.tocoo()
    boundary = np.unique(a.row[labels[a.row] != labels[a.col]])
    if not len(boundary):
        return np.full(len(faces), np.inf)
    return csgraph.dijkstra(adjacency, unweighted=True, indices=boundary, min_only=True)


def error_by_band(pred: np.ndarray, truth: np.ndarray, areas: np.ndarray, rings: np.ndarray) -> dict[str, float]:
    """The wrong area in % of the mesh's area: `err` in all, `err_<band>` in each of BANDS (they sum to `err`)."""
    wrong = np.asarray(pred) != np.asarray(truth)
    areas = np.asarray(areas, np.float64)
    total = areas.sum()
    out = {"err": 100.0 * areas[wrong].sum() / total}
    for (lo, hi), name in zip(BANDS, BAND_NAMES):
        band = (rings >= lo) & (rings <= (math.inf if hi is None else hi))
        out[f"err_{name}"] = 100.0 * areas[wrong & band].sum() / total
    return out


def where_errors_lie(table: Table, overrides=()) -> tuple[pd.DataFrame, int, int]:
    """One row per test mesh of the table (COLUMNS) whose labelling can be read: a run's per-face predictions
    (refined under report.metric=acc, the argmax under acc_raw) or a predictions column's file. Returns the
    frame, how many of the table's test meshes had no per-face labels to read, and how many were a predictions
    column's under acc_raw (a labelling on disk has no argmax before refinement)."""
    from mlflow import MlflowClient

    from meshseg.config import run_config
    from meshseg.data.datasets import build_dataset
    from meshseg.report.predictions import labelling
    from meshseg.report.runs import run_predictions
    from meshseg.tracking import store_uri

    prefix = "labels_" if table.metric == "acc" else "labels_raw_"
    m = table.manifest
    groups, columns = {g.name: g for g in m.groups}, {c.key: c for c in m.columns}
    rows, unlabelled, raw_files, loaded, datasets = [], 0, 0, {}, {}
    for (group, key), part in table.meshes.groupby(["group", "column"], sort=False):
        column = columns[key]
        if column.predictions is not None and table.metric != "acc":
            raw_files += len(part)
            continue
        cfg = run_config([*m.cell_overrides(groups[group], column), *overrides])
        spec = OmegaConf.to_yaml(cfg.dataset)
        if spec not in datasets:
            datasets[spec] = build_dataset(cfg.dataset)
        dataset = datasets[spec]
        client = MlflowClient(tracking_uri=store_uri(cfg.tracking.uri))
        for run_id, meshes in part.groupby("run_id", sort=False, dropna=False):
            arrays = None if column.predictions is not None else run_predictions(client, run_id)
            for r in meshes.itertuples():
                if column.predictions is None and (arrays is None or f"{prefix}{r.mesh}" not in arrays):
                    unlabelled += 1
                    continue
                key_mesh = (spec, r.category, r.mesh)  # every column of a set scores the same meshes: load once
                if key_mesh not in loaded:
                    mesh = dataset.load(r.category, r.mesh)
                    loaded[key_mesh] = mesh, boundary_rings(mesh.faces, mesh.labels)
                mesh, rings = loaded[key_mesh]
                pred = (
                    labelling(column.predictions, mesh, cfg.paths.cache_dir)
                    if column.predictions is not None
                    else arrays[f"{prefix}{r.mesh}"]
                )
                bands = error_by_band(pred, mesh.labels, mesh.face_areas, rings)
                rows.append({"group": group, "row": r.row, "column": key, "mesh": r.mesh, **bands})
    if unlabelled or raw_files:
        log.info(
            "where errors lie: %d test meshes left out (%d without per-face labels here, %d labellings under acc_raw)",
            unlabelled + raw_files,
            unlabelled,
            raw_files,
        )
    return pd.DataFrame(rows, columns=list(COLUMNS)), unlabelled, raw_files


def summary(frame: pd.DataFrame, pairs) -> pd.DataFrame:
    """Mean over meshes of each column's wrong area by band (`minus` empty), then of each pair's accuracy
    difference a − b by band (points; over the meshes both have, as the paired comparison takes them): one
    line each, `column` a and `minus` b."""
    bands = ["err", *(f"err_{b}" for b in BAND_NAMES)]
    lines = []
    for key, part in frame.groupby("column", sort=False):
        lines.append({"column": key, "minus": "", "meshes": len(part), **part[bands].mean().to_dict()})
    for a, b in pairs:
        keys = ["group", "row", "mesh"]
        both = frame[frame["column"] == a].merge(frame[frame["column"] == b], on=keys, suffixes=("_a", "_b"))
        if len(both):
            gap = {c: float((both[f"{c}_b"] - both[f"{c}_a"]).mean()) for c in bands}
            lines.append({"column": a, "minus": b, "meshes": len(both), **gap})
    return pd.DataFrame(lines, columns=["column", "minus", "meshes", *bands])
