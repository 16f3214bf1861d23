"""scripts/ring_information.py: how much X^k adds to X^1, checked where the answer is known."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import trimesh

spec = importlib.util.spec_from_file_location(
    "ring_information", Path(__file__).parents[1] / "scripts/ring_information.py"
)
ring_information = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ring_information)


def test_ring_information_on_a_closed_sphere():
    m = trimesh.creation.icosphere(subdivisions=4)  # 5,120 faces, closed: every face has 3 edge neighbours
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    centres = V[F].mean(axis=1)
    rng = np.random.default_rng(0)
    X = np.column_stack([rng.standard_normal(len(F)), centres[:, 0], np.full(len(F), 7.0)])
    k2, k3 = ring_information.ring_information(V, F, X, scales=3)
    assert k2["faces"] == 4.0  # the face and its 3 edge neighbours
    assert 9.5 < k3["faces"] <= 10.0  # 1 + 3 + 6 on a regular triangulation; fewer round the 12 valence-5 vertices
    # an iid column: the mean of n values, the face's own among them, differs from it by (n-1)/n of its variance
    assert abs(k2["columns"][0] - 0.75) < 0.04 and abs(k3["columns"][0] - 0.9) < 0.04
    # a smooth column (x of the centre) barely moves at these scales; a constant one carries nothing (NaN)
    assert k2["columns"][1] < 0.01 and k3["columns"][1] < 0.02
    assert np.isnan(k2["columns"][2]) and k2["new"] == np.nanmean(k2["columns"])
    # reach: the ring's farthest centre, in % of the bounding box diagonal; adjacent centres of equilateral
    # triangles lie edge / sqrt(3) apart, and the dual graph is hexagonal: two steps zig-zag, reaching edge
    edge, diagonal = float(np.mean(m.edges_unique_length)), float(np.linalg.norm(np.ptp(V, axis=0)))
    assert abs(k2["reach"] / 100 * diagonal / (edge / np.sqrt(3)) - 1) < 0.1
    assert abs(k3["reach"] / 100 * diagonal / edge - 1) < 0.1
