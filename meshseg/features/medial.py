"""Distance from the medial surface (Liu et al. 2009's volumetric shape image, "VSI") as Kalogerakis
et al. 2010 compute it: `dms`, 24 columns.

The medial point behind a face is estimated from its SDF rays (`shape_diameter.py`): half the
shortest of them, along the inward normal. From there rays go out in all directions and their
lengths to the surface describe how far the surface is from that point of the medial surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from meshseg.features.registry import register
from meshseg.features.shape_diameter import (
    BASES,
    STATISTICS,
    RaySetup,
    fill_invalid,
    log_transforms,
    normalise_columns,
    ray_fan,
    ray_statistics,
    sdf_rays,
)

#: polar angles (degrees from the inward normal) of the rings of rays cast from the medial point
RINGS = (45, 90, 135)


@dataclass(frozen=True)
class DMSSettings:
    """The `dms` group's parameters (see `dms`)."""

    sdf_rays_per_cone: int = 8
    rays_per_ring: int = 8
    normals: str = "vertex"
    frame: str = "principal"
    outlier_quantile: float = 0.95


def medial_rays(setup: RaySetup, sdf_rays_per_cone: int, rays_per_ring: int) -> np.ndarray:
    """(F, 1 + 3k) per face: the distance from the face centre to its medial point (half the
    shortest SDF ray within 45°), then the ray lengths from the medial point on the rings at 45°,
    90° and 135° from the inward normal, k rays each, azimuths from the face's frame."""
    inward = -setup.n
    half = 0.5 * sdf_rays(setup, sdf_rays_per_cone).min(axis=1)
    centre = setup.origins + half[:, None] * inward
    cols = [half[:, None]]
    for ring in RINGS:
        for d in ray_fan(inward, setup.t1, setup.t2, ring, rays_per_ring):
            # the medial point is off the surface: every face, the own one included, may be hit
            cols.append(setup.cast(centre, d, False)[:, None])
    return np.concatenate(cols, axis=1)


def medial_distances(V: np.ndarray, F: np.ndarray, settings: DMSSettings | None = None) -> np.ndarray:
    """Raw distances (F, 1 + 3·rays_per_ring) in the mesh's units, before the per-mesh
    normalisation: see `medial_rays`."""
    s = settings or DMSSettings()
    return medial_rays(RaySetup(V, F, s.normals, s.frame), s.sdf_rays_per_cone, s.rays_per_ring)


def _columns() -> list[str]:
    return [f"VSI b{b} {s}" for b in BASES for s in STATISTICS]


@register("dms", dim=24, columns=_columns(), settings=DMSSettings)
def dms(V: np.ndarray, F: np.ndarray, settings: DMSSettings | None = None) -> np.ndarray:
    """Distance from the medial surface, 24 columns = 4 transforms × 6 statistics.

    Per face the 1 + 3·`rays_per_ring` distances of `medial_rays` (the face-to-medial-point
    distance and the rays from the medial point; a ray that hits nothing has the bounding-box
    diagonal, see `shape_diameter`) give mean, mean2 = mean of squares, mean4 = mean of 4th
    powers, meansqrt, meansqrtsqrt (means of square and 4th roots) and median. Per mesh each
    column is clamped at its `outlier_quantile` over the faces and divided by its maximum; b1
    are these, b2/b4/b8 are log(x·b + 1)/log(b + 1). Order: base, statistic.
    """
    s = settings or DMSSettings()
    setup = RaySetup(V, F, s.normals, s.frame)
    S = ray_statistics(medial_rays(setup, s.sdf_rays_per_cone, s.rays_per_ring))
    S = fill_invalid(S, setup.F, setup.valid)
    return log_transforms(normalise_columns(S, s.outlier_quantile)).astype(np.float32)
