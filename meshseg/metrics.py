"""The paper's accuracy (§4): area-weighted fraction of correctly labelled surface, and its aggregates."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Hashable, Iterable

import numpy as np


def area_weighted_accuracy(pred: np.ndarray, gt: np.ndarray, areas: np.ndarray) -> float:
    """sum_t a_t [l_t == gt_t] / sum_t a_t over the faces t of one mesh."""
    pred, gt, areas = np.asarray(pred), np.asarray(gt), np.asarray(areas, np.float64)
    if not pred.shape == gt.shape == areas.shape or pred.ndim != 1:
        raise ValueError(f"pred {pred.shape}, gt {gt.shape} and areas {areas.shape} must be equal-length vectors")
    total = areas.sum()
    if not total > 0:
        raise ValueError("total face area is zero: accuracy is undefined")
    return float(areas[pred == gt].sum() / total)


def area_accuracy(mesh, labels: np.ndarray) -> float:
    """The accuracy of per-face `labels` on a mesh with ground truth (labels, face_areas): what refine.search
    scores its grid points by."""
    return area_weighted_accuracy(labels, mesh.labels, mesh.face_areas)


def confusion_matrix(pred: np.ndarray, gt: np.ndarray, n_classes: int, weights: np.ndarray | None = None) -> np.ndarray:
    """C[i, j] = weight (face count, or area if `weights` are areas) with ground truth i predicted j."""
    pred, gt = np.asarray(pred, np.int64), np.asarray(gt, np.int64)
    w = np.ones(len(gt)) if weights is None else np.asarray(weights, np.float64)
    return np.bincount(gt * n_classes + pred, weights=w, minlength=n_classes * n_classes).reshape(n_classes, n_classes)


def mean_by(values: Iterable[float], keys: Iterable[Hashable]) -> dict[Hashable, float]:
    """Mean of per-mesh accuracies grouped by key (a fold, a category, a (method, category) cell).

    A category's figure is the mean over all test meshes of all its folds, as in the paper's tables.
    """
    groups: dict[Hashable, list[float]] = defaultdict(list)
    for v, k in zip(values, keys, strict=True):
        groups[k].append(float(v))
    return {k: float(np.mean(v)) for k, v in groups.items()}


def mesh_scores(meshes, raw_labels, labels) -> list[dict]:
    """One row per test mesh: id, faces, area, accuracy before (`acc_raw`) and after (`acc`) refinement."""
    return [
        {
            "mesh": m.id,
            "faces": m.n_faces,
            "area": float(m.face_areas.sum()),
            "acc_raw": area_weighted_accuracy(raw, m.labels, m.face_areas),
            "acc": area_weighted_accuracy(lab, m.labels, m.face_areas),
        }
        for m, raw, lab in zip(meshes, raw_labels, labels, strict=True)
    ]
