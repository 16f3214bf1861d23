"""Curvature features: Kalogerakis et al. 2010's multi-scale quadric-fit curvatures (`curvature`,
64 columns) and pointwise Gaussian curvature (`gc`, 1 column).

The neighbourhoods are the 2010 code's (`neighbourhoods.py`, shared with `pca`); its units and
face normals are `geometry.kalogerakis_normalize` and `geometry.smoothed_face_normals`.
"""

from __future__ import annotations

from dataclasses import dataclass

import igl
import numpy as np
from threadpoolctl import threadpool_limits

from meshseg.errors import ConfigError
from meshseg.features.geometry import (
    clip_outliers,
    face_areas,
    face_centers,
    kalogerakis_normalize,
    per_face_normals,
    smoothed_face_normals,
    vertex_to_face,
)
from meshseg.features.neighbourhoods import face_neighbours, geodesic_balls
from meshseg.features.registry import register

CURVATURE_VALUES = ("k1", "k2", "k1-k2", "K1", "K2", "K1-K2", "H", "K")
CURVATURE_COLUMNS = [
    f"CUR s{s} {v}" for s in range(4) for v in CURVATURE_VALUES + tuple(f"|{v}|" for v in CURVATURE_VALUES)
]


# ---------------------------------------------------------------------------------------------
# curvature (Kalogerakis et al. 2010)


def principal_curvatures(
    V: np.ndarray,
    F: np.ndarray,
    radii,
    *,
    max_neighbors: int = 256,
    min_faces: int = 3,
    smoothed_normals: bool = True,
) -> np.ndarray:
    """(F, len(radii), 2) principal curvatures k1 >= k2 of a quadric fitted around each face.

    As in the 2010 code: the neighbours are the face's geodesic ball (`geodesic_balls` with its
    normal test and `min_faces`), the face itself excluded; in the frame (t, s, n) of the face
    (n its normal, t along (v0 - v1) x n) each neighbour j, at d = c_face - c_j, gives three rows
    weighted by its area a_j: the height z = a x^2/2 + b x y + c y^2/2 and the two slopes of its
    normal, a x + b y = -n_x/n_z and b x + c y = -n_y/n_z; k1, k2 are the eigenvalues of
    [[a, b], [b, c]]. Because d points from the neighbour to the face, a convex region with
    outward normals has k > 0.
    """
    c = face_centers(V, F)
    n = smoothed_face_normals(V, F) if smoothed_normals else per_face_normals(V, F)
    a = face_areas(V, F)
    t = np.cross(V[F[:, 0]] - V[F[:, 1]], n)
    t_norm = np.linalg.norm(t, axis=1, keepdims=True)
    t = np.divide(t, t_norm, out=np.zeros_like(t), where=t_norm > 0)
    s = np.cross(t, n)
    frame = np.stack([t, s, n], axis=2)  # (F, 3, 3): columns t, s, n
    out = np.zeros((len(F), len(radii), 2))
    for rows, J, masks in geodesic_balls(
        c, face_neighbours(V, F), radii, max_neighbors=max_neighbors, min_faces=min_faces, normals=n
    ):
        Jn = J[:, 1:]
        B, k = Jn.shape
        local = np.matmul(c[rows, None, :] - c[Jn], frame[rows])  # (B, k, 3): x, y, z
        nloc = np.matmul(n[Jn], frame[rows])
        x, y, z = local[..., 0], local[..., 1], local[..., 2]
        # the normal test keeps n_z > 0 except for the forced first faces; keep their slopes finite
        nz = nloc[..., 2]
        nz = np.where(np.abs(nz) < 1e-6, np.where(nz < 0, -1e-6, 1e-6), nz)
        u, v = -nloc[..., 0] / nz, -nloc[..., 1] / nz
        # the 15 weighted sums that make the 3x3 normal equations of the stacked rows
        Q = np.empty((B, k, 15))
        xx, xy, yy = (
            np.multiply(x, x, out=Q[..., 5]),
            np.multiply(x, y, out=Q[..., 6]),
            np.multiply(y, y, out=Q[..., 7]),
        )
        products = [(xx, xx), (xx, xy), (xx, yy), (xy, yy), (yy, yy)]  # Q[..., 0:5]: the 4th-order moments
        products += [(z, xx), (z, xy), (z, yy), (u, x), (u, y), (v, x), (v, y)]  # Q[..., 8:15]: the right side
        for q, (left, right) in zip([0, 1, 2, 3, 4, *range(8, 15)], products):
            np.multiply(left, right, out=Q[..., q])
        a1 = a[Jn]
        a2 = a1**2
        W = np.empty((B, len(masks), k))
        W1 = np.empty((B, len(masks), k))
        for i, m in enumerate(masks):
            np.multiply(m[:, 1:], a2, out=W[:, i])
            np.multiply(m[:, 1:], a1, out=W1[:, i])
        # absolute column sums of the weighted row matrix: its 1-norm is the original's rank cutoff
        ax, ay = np.abs(x), np.abs(y)
        cols = np.stack([0.5 * xx + ax, np.abs(xy) + ax + ay, 0.5 * yy + ay], axis=-1)
        out[rows] = _solve_quadric(np.matmul(W, Q), np.matmul(W1, cols).max(axis=-1))
    return out


def _solve_quadric(S: np.ndarray, rcond: np.ndarray) -> np.ndarray:
    """(..., 15) weighted sums -> (..., 2) eigenvalues of the fitted Hessian, larger first.

    The original solves the stacked rows with LAPACK dgelsy and RCOND = the rows' 1-norm, so a
    direction whose singular value is below RCOND x the largest is dropped (minimum-norm
    solution): a near-degenerate neighbourhood (centres along a thin wire) gets a tame fit.
    Here: the same cut on the singular values (square roots of the normal matrix's eigenvalues).
    """
    x4, x3y, x2y2, xy3, y4, x2, xy, y2, zx2, zxy, zy2, ux, uy, vx, vy = np.moveaxis(S, -1, 0)
    A = np.empty(S.shape[:-1] + (3, 3))
    A[..., 0, 0] = x4 / 4 + x2
    A[..., 0, 1] = A[..., 1, 0] = x3y / 2 + xy
    A[..., 0, 2] = A[..., 2, 0] = x2y2 / 4
    A[..., 1, 1] = x2y2 + x2 + y2
    A[..., 1, 2] = A[..., 2, 1] = xy3 / 2 + xy
    A[..., 2, 2] = y4 / 4 + y2
    rhs = np.stack([zx2 / 2 + ux, zxy + uy + vx, zy2 / 2 + vy], axis=-1)
    lam, vec = np.linalg.eigh(A)
    keep = lam > np.maximum(rcond**2, 1e-15)[..., None] * lam[..., -1:]
    inv = np.divide(1.0, lam, out=np.zeros_like(lam), where=keep & (lam > 0))
    coef = np.einsum("...ij,...j,...kj,...k->...i", vec, inv, vec, rhs)
    ha, hb, hc = coef[..., 0], coef[..., 1], coef[..., 2]
    mean = (ha + hc) / 2
    root = np.sqrt(np.maximum(((ha - hc) / 2) ** 2 + hb**2, 0.0))
    return np.stack([mean + root, mean - root], axis=-1)


def curvature_values(k1: np.ndarray, k2: np.ndarray) -> np.ndarray:
    """The 16 per-scale values of the 2010 code from k1 >= k2: k1, k2, k1-k2; K1, K2, K1-K2 (the
    same ordered by |k|, |K1| >= |K2|); H = (k1+k2)/2; K = k1 k2; then the 8 absolute values."""
    swap = np.abs(k1) < np.abs(k2)
    K1, K2 = np.where(swap, k2, k1), np.where(swap, k1, k2)
    signed = [k1, k2, k1 - k2, K1, K2, K1 - K2, (k1 + k2) / 2, k1 * k2]
    return np.stack(signed + [np.abs(x) for x in signed], axis=-1)


def smooth_across_edges(X: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """Mean of each face's row and its edge-adjacent faces' rows (the 2010 code's last step; it
    always divides by 4, reading past the array on a boundary edge: here missing faces are left out)."""
    Xp = np.vstack([X, np.zeros((1, X.shape[1]))])
    idx = np.where(nbr < 0, len(X), nbr)
    count = 1 + (nbr >= 0).sum(axis=1, keepdims=True)
    return (X + Xp[idx].sum(axis=1)) / count


@dataclass(frozen=True)
class CurvatureSettings:
    """The `curvature` group's parameters (see `curvature`)."""

    radii: tuple = (0.01, 0.02, 0.05, 0.10)
    max_neighbors: int = 256
    min_faces: int = 3
    smoothed_normals: bool = True
    clip: bool = True
    smooth: bool = True


@register("curvature", 64, version="1", columns=CURVATURE_COLUMNS, settings=CurvatureSettings)
def curvature(V: np.ndarray, F: np.ndarray, settings: CurvatureSettings | None = None) -> np.ndarray:
    """Kalogerakis et al. 2010 curvature, 16 columns per radius (columns.txt 0-63).

    Per radius (geodesic, in `kalogerakis_normalize` units, so the columns are scale-invariant):
    k1, k2, k1-k2, K1, K2, K1-K2, H, K and their absolute values (`curvature_values`) from a
    quadric fitted to the face's geodesic neighbourhood (`principal_curvatures`, at most
    `max_neighbors` faces, the first `min_faces` always taken). Per mesh and column, values are
    clipped to the 5-95 % order statistics (absolute columns: to the 95 % one), then averaged with
    the edge-adjacent faces' values, as the original does (`clip`, `smooth`). Everything is
    per face: no vertex-to-face mapping. `smoothed_normals=False` uses the triangles' own normals
    instead of the original's smoothed ones (`smoothed_face_normals`).
    """
    s = settings or CurvatureSettings()
    if len(s.radii) != 4:
        raise ConfigError(f"curvature: needs 4 radii (the group has 4 x 16 columns), got {list(s.radii)}")
    Vn = kalogerakis_normalize(V, F)
    with threadpool_limits(limits=1, user_api="blas"):  # many small BLAS calls: threads only add sync overhead
        k = principal_curvatures(
            Vn, F, s.radii, max_neighbors=s.max_neighbors, min_faces=s.min_faces, smoothed_normals=s.smoothed_normals
        )
    nbr = face_neighbours(Vn, F).ids
    signed = np.arange(16) < 8
    cols = []
    for i in range(len(s.radii)):
        X = curvature_values(k[:, i, 0], k[:, i, 1])
        if s.clip:
            X = clip_outliers(X, signed)
        if s.smooth:
            X = smooth_across_edges(X, nbr)
        cols.append(X)
    return np.concatenate(cols, axis=1).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Gaussian curvature (paper's GC)


@register("gc", 1, version="1", columns=["GC"])
def gc(V: np.ndarray, F: np.ndarray, *, min_area: float = 1e-8) -> np.ndarray:
    """Pointwise Gaussian curvature: the angle defect at each vertex (`igl.gaussian_curvature`)
    divided by its barycentric area (`igl.massmatrix`, a third of the adjacent faces' areas), then
    the mean over the face's three vertices. No per-mesh normalisation: on a sphere of radius r it
    is 1/r^2, and it scales as 1/s^2 with the mesh. A vertex whose area is below `min_area` x the
    mean vertex area (zero-area faces only) uses that floor, so the value stays finite."""
    # Valid but unusual meshes: vertices no face uses are dropped (igl sizes its outputs by the largest
    # index), and faces of zero area (repeated or coincident vertices) have no angles, so they take no
    # part in the defect and the areas; their own value is the mean over their vertices like any face's.
    used, Fc = np.unique(np.asarray(F, dtype=np.int64), return_inverse=True)
    Fc = np.ascontiguousarray(Fc.reshape(-1, 3))
    Vc = np.ascontiguousarray(np.asarray(V, dtype=np.float64)[used])
    n = len(Vc)
    good = face_areas(Vc, Fc) > 0
    defect, area = np.zeros(n), np.zeros(n)
    if good.any():
        Fg = np.ascontiguousarray(Fc[good])
        d = igl.gaussian_curvature(Vc, Fg)
        a = igl.massmatrix(Vc, Fg, igl.MASSMATRIX_TYPE_BARYCENTRIC).diagonal()
        defect[: len(d)], area[: len(a)] = d[:n], a[:n]
    touched = np.zeros(n, bool)
    touched[Fc[good].ravel()] = True
    defect[~touched] = 0.0  # a vertex of degenerate faces only: no curvature can be measured there
    floor = min_area * (area[touched].mean() if touched.any() and area[touched].mean() > 0 else 1.0)
    k = defect / np.maximum(area, floor)
    return vertex_to_face(k, Fc)[:, None].astype(np.float32)
