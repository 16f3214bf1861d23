"""The pictures a fold's run shows in the MLflow UI: label renders of some test meshes (predicted beside
ground truth) and the area-weighted confusion matrix."""

from __future__ import annotations

import numpy as np


def pictures(meshes, labels, rows: list[dict], n: int) -> dict[str, bytes]:
    """{artifact path: PNG}: renders/mesh_<id>.png for up to `n` test meshes — the worst, the best, then
    the median by accuracy (`rows`: the per-mesh table), so that what went wrong is in view — and
    confusion.png, the area-weighted confusion over every test mesh."""
    from meshseg.metrics import confusion_matrix
    from meshseg.render import confusion_png, label_comparison_png

    names = list(meshes[0].label_names)
    order = np.argsort([r["acc"] for r in rows], kind="stable")
    picks = list(dict.fromkeys([order[0], order[-1], order[len(order) // 2], *order]))[:n]
    confusion = sum(confusion_matrix(lab, m.labels, len(names), m.face_areas) for m, lab in zip(meshes, labels))
    out = {}
    for i in picks:
        m = meshes[i]
        title = f"{m.category} mesh {m.id}"
        out[f"renders/mesh_{m.id}.png"] = label_comparison_png(
            m.vertices, m.faces, labels[i], m.labels, names, title=title
        )
    out["confusion.png"] = confusion_png(confusion, names, title="area-weighted, all test meshes")
    return out
