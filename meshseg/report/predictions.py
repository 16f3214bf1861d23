"""A column from predictions on disk (e.g. Kalogerakis et al. 2010's released leave-one-out labellings),
scored mesh by mesh with meshseg's own metric, exactly as a run's predictions are (`metrics.mesh_scores`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from meshseg.data.archive import resolve_root
from meshseg.data.io import read_psb_labels
from meshseg.errors import MeshDataError
from meshseg.metrics import area_weighted_accuracy
from meshseg.report.manifest import Predictions


def _folder(spec: Predictions, cache_dir: str) -> Path:
    root = resolve_root(spec.path, cache_dir, setting="predictions.path")
    found = next(iter(sorted(root.rglob("*.lab"))), None)
    if found is None:
        raise MeshDataError(spec.path, "holds no <id>.lab labelling")
    return found.parent


def score(spec: Predictions, dataset, category: str, mesh_ids, cache_dir: str) -> list[tuple[str, float]]:
    """(mesh id, area-weighted accuracy in %) of each mesh's labelling on disk against the dataset's ground
    truth. A missing file, a face count that differs or a label name the category lacks is one error naming
    the file."""
    folder = _folder(spec, cache_dir)
    out = []
    for mesh_id in mesh_ids:
        mesh = dataset.load(category, mesh_id)
        labels = _read(folder, mesh)
        out.append((mesh_id, 100.0 * area_weighted_accuracy(labels, mesh.labels, mesh.face_areas)))
    return out


def labelling(spec: Predictions, mesh, cache_dir: str) -> np.ndarray:
    """The labelling on disk of `mesh` (a dataset's Mesh), one index into its label names per face: what
    `score` scores, e.g. to render it."""
    return _read(_folder(spec, cache_dir), mesh)


def _read(folder: Path, mesh) -> np.ndarray:
    path = folder / f"{mesh.id}.lab"
    if not path.is_file():
        raise MeshDataError(path, f"no labelling of {mesh.category} mesh {mesh.id}")
    local, names = read_psb_labels(path, mesh.n_faces)
    unknown = [n for n in names if n not in mesh.label_names]
    if unknown:
        raise MeshDataError(path, f"labels {unknown} are not in {mesh.category}'s {list(mesh.label_names)}")
    return np.array([mesh.label_names.index(n) for n in names], np.int64)[local]
