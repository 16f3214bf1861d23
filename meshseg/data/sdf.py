"""Signed distances of primitive shapes, the parts synthetic meshes are made of. ``p`` is an (N, 3) array of
points; each function returns (N,) distances, negative inside. Formulas follow Inigo Quilez's distance
functions."""

from __future__ import annotations

import numpy as np


def _length(*components: np.ndarray) -> np.ndarray:
    return np.sqrt(sum(c * c for c in components))


def sd_sphere(p: np.ndarray, center, radius: float) -> np.ndarray:
    return _length(*(p - center).T) - radius


def sd_ellipsoid(p: np.ndarray, center, radii) -> np.ndarray:
    # Not an exact distance, but exact on the surface and a good bound near it,
    # which is all marching cubes and the argmin labelling need.
    q = (p - center).T
    radii = np.asarray(radii, dtype=float)
    k0 = _length(*(q / radii[:, None]))
    k1 = _length(*(q / (radii**2)[:, None]))
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)


def sd_round_box(p: np.ndarray, center, half, rounding: float = 0.0) -> np.ndarray:
    q = np.abs(p - center) - (np.asarray(half, dtype=float) - rounding)
    outside = _length(*np.maximum(q, 0.0).T)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside - rounding


def sd_capsule(p: np.ndarray, a, b, radius: float) -> np.ndarray:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    pa, ba = p - a, b - a
    t = np.clip(pa @ ba / (ba @ ba), 0.0, 1.0)
    return _length(*(pa - t[:, None] * ba).T) - radius


def sd_cylinder_z(p: np.ndarray, center, radius: float, half_height: float) -> np.ndarray:
    """Capped cylinder with its axis along z."""
    d = p - center
    qr = np.hypot(d[:, 0], d[:, 1]) - radius
    qz = np.abs(d[:, 2]) - half_height
    return _length(np.maximum(qr, 0.0), np.maximum(qz, 0.0)) + np.minimum(np.maximum(qr, qz), 0.0)


def sd_torus_xz(p: np.ndarray, center, major: float, minor: float, stretch: float = 0.0) -> np.ndarray:
    """Torus lying in the xz plane (axis y), optionally elongated by +-`stretch` along z."""
    d = p - center
    dz = d[:, 2] - np.clip(d[:, 2], -stretch, stretch)  # elongation keeps the SDF exact
    return np.hypot(np.hypot(d[:, 0], dz) - major, d[:, 1]) - minor


def _segment_distance_2d(x, y, a, b) -> np.ndarray:
    ax, ay, bx, by = *a, *b
    ex, ey = bx - ax, by - ay
    t = np.clip(((x - ax) * ex + (y - ay) * ey) / (ex * ex + ey * ey), 0.0, 1.0)
    return np.hypot(x - ax - t * ex, y - ay - t * ey)


def sd_open_shell_z(p: np.ndarray, r_bottom: float, r_top: float, height: float, thickness: float) -> np.ndarray:
    """Open-topped cup shell: the z-axis surface of revolution of the profile
    (0, 0) -> (r_bottom, 0) -> (r_top, height), thickened by `thickness`.

    Thickening a surface (rather than subtracting two cylinders) gives a uniform wall
    and bottom with a rounded rim, which stays watertight at coarser grid spacings.
    """
    r, z = np.hypot(p[:, 0], p[:, 1]), p[:, 2]
    corner = (r_bottom, 0.0)
    d = np.minimum(_segment_distance_2d(r, z, (0.0, 0.0), corner), _segment_distance_2d(r, z, corner, (r_top, height)))
    return d - thickness / 2
