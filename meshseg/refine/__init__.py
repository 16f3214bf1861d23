"""Refinement of per-face probabilities into labels (paper §3.5). `none`: the argmax."""

from __future__ import annotations

import numpy as np

from meshseg.data.mesh import Mesh

METHODS = ("none",)


def refine_labels(mesh: Mesh, probabilities: np.ndarray, cfg) -> np.ndarray:
    """Labels (faces,) for `mesh` from its (faces, classes) probabilities under refinement `cfg`."""
    if cfg.name == "none":
        return probabilities.argmax(axis=1)
    raise ValueError(f"unknown refinement {cfg.name!r}; known: {list(METHODS)}")
