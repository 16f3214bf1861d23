"""Refinement of per-face probabilities into labels (paper §3.5): `refinement.py` holds the classes the
configs name, `graphcut.py` the science."""

from meshseg.refine.refinement import (
    Argmax,
    GraphCutAGD,
    GraphCutClassic,
    Refinement,
    build_refinement,
    refine_labels,
)

__all__ = ["Argmax", "GraphCutAGD", "GraphCutClassic", "Refinement", "build_refinement", "refine_labels"]
