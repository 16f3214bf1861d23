"""Spin images (Johnson & Hebert 1999) as Kalogerakis et al. 2010 compute them: `spin_images`, 100 columns.

For a face with centre p and unit normal n, a surface point x has the cylindrical coordinates
β = n·(x − p) (signed height along the normal) and α = sqrt(|x − p|² − β²) (distance from the
normal line). The spin image is a 10 × 10 histogram of (β, α) over the surface, each point
weighted by the share of surface area it stands for.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from meshseg.features.geometry import (
    face_areas,
    face_centers,
    farthest_point_sampling,
    kalogerakis_units,
    vertex_normals,
)
from meshseg.features.registry import register
from meshseg.features.shape_diameter import face_normals

BINS = 10
#: Gaussian soft assignment of the original: weight exp(−d²/0.2) to a bin whose centre is d bin
#: widths away, dropped below 0.02 (so only the ≤ 2 nearest bins per axis can receive weight)
_KERNEL_DIV, _KERNEL_MIN = 0.2, 0.02
#: |cos| under which a point's normal counts as perpendicular to the face's (float32 rounding ~1e-7)
_FACING = np.float32(1e-4)
#: relative difference under which two distances count as a tie (rounding is ~1e-16)
_TIE = 1e-9
#: (faces × samples) pairs handled at once: small enough to stay in cache (about 60 bytes a pair);
#: 8x more is 4x slower
_PAIRS_PER_BLOCK = 1 << 16


def vertex_area_weights(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Each vertex's weight: the summed area of its faces over the sum of that over all vertices
    (the original's `vertexFaceAreas`); 0 for a vertex no face with area touches."""
    w = np.bincount(F.ravel(), np.repeat(face_areas(V, F), 3), minlength=len(V))
    return w / w.sum() if w.sum() > 0 else w


def spin_samples(V: np.ndarray, vn: np.ndarray, w: np.ndarray, n_samples: int, bin_size: float):
    """Surface points, their normals and weights (sum 1) that the images histogram.

    The original uses every vertex; that is kept when there are at most `n_samples` vertices
    with weight. Otherwise `n_samples` of them are chosen by farthest-point sampling in
    (position, bin_size · normal) space — so the two sides of a thin part are both sampled —
    and each carries the weight of the vertices nearest to it in that space (its Voronoi cell).
    The choice depends on the geometry only, not on the order of faces or a rigid motion.
    """
    keep = np.flatnonzero(w > 0)
    if len(keep) <= n_samples:
        return V[keep], vn[keep], w[keep]
    X = np.concatenate([V[keep], bin_size * vn[keep]], axis=1)
    seeds = farthest_point_sampling(X, n_samples, tie=_TIE)
    # nearest seed; a vertex equidistant (to rounding) from two seeds goes to the earlier one
    d, near = cKDTree(X[seeds]).query(X, k=2)
    tie = d[:, 1] - d[:, 0] <= _TIE * d[:, 1]
    cell = np.where(tie, near.min(axis=1), near[:, 0])
    return V[keep][seeds], vn[keep][seeds], np.bincount(cell, w[keep], minlength=n_samples)


def spin_histograms(
    C: np.ndarray, N: np.ndarray, P: np.ndarray, PN: np.ndarray, W: np.ndarray, support: float
) -> np.ndarray:
    """(F, 100) spin images of the faces (centres C, normals N) over points P (normals PN,
    weights W): rows are β bins from +support (bin 0) down to −support, columns α bins from 0 to
    support, flattened β-major. A point counts only if its normal faces the same side as the
    face's (PN·N ≥ 0, to within 1e-4); it spreads its weight over the bins near (β, α) with the
    original's Gaussian kernel normalised to sum 1, so it adds exactly its weight to the image,
    or nothing when it lies outside the support. Float32 pair geometry, as the original."""
    bin_size = np.float32(support / BINS)
    nb = BINS * BINS
    out = np.zeros((len(C), nb))
    P32, PN32, W32 = P.astype(np.float32), PN.astype(np.float32), W.astype(np.float32)
    P2 = np.einsum("ij,ij->i", P32, P32)
    reach = np.float32(0.9)  # a point farther than 0.885 bin widths from every bin centre gets nothing
    step = max(1, _PAIRS_PER_BLOCK // max(len(P), 1))
    for s in range(0, len(C), step):
        c, n = C[s : s + step].astype(np.float32), N[s : s + step].astype(np.float32)
        b = len(c)
        beta = n @ P32.T
        beta -= np.einsum("ij,ij->i", n, c)[:, None]
        r2 = c @ P32.T
        r2 *= -2
        r2 += P2[None]
        r2 += np.einsum("ij,ij->i", c, c)[:, None]
        r2 -= beta * beta
        np.maximum(r2, 0, out=r2)
        # continuous bin coordinates measured from the first bin's centre
        jc = np.sqrt(r2, out=r2)
        jc /= bin_size
        jc -= np.float32(0.5)
        ic = beta
        ic *= np.float32(-0.5) / bin_size
        ic += np.float32(support / 2) / bin_size - np.float32(0.5)
        # ">= 0" in the original; CAD-like meshes have many exactly perpendicular normals, which
        # rounding after a rigid motion would flip, so within 1e-4 counts as facing
        keep = (n @ PN32.T) >= -_FACING
        keep &= (ic > -reach) & (ic < BINS - 1 + reach) & (jc < BINS - 1 + reach)
        pair = np.flatnonzero(keep)
        if not len(pair):
            continue
        row = pair // len(P)
        ic, jc, w = ic.ravel()[pair], jc.ravel()[pair], W32[pair - row * len(P)]
        x0, y0 = np.floor(ic), np.floor(jc)
        fx, fy = ic - x0, jc - y0
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        # the two nearest bins per axis (x0 and x0 + 1); a bin off the image gets no weight
        gx = (_kernel(fx) * (x0 >= 0), _kernel(1 - fx) * (x0 < BINS - 1))
        gy = (_kernel(fy) * (y0 >= 0), _kernel(1 - fy) * (y0 < BINS - 1))
        corners = []
        for i in (0, 1):
            for j in (0, 1):
                g = gx[i] * gy[j]
                g[g < _KERNEL_MIN] = 0
                corners.append((i * BINS + j, g))
        total = sum(g for _, g in corners)
        scale = np.divide(w, total, out=np.zeros_like(total), where=total > 0)
        # flat index of corner (0, 0), shifted by BINS + 1 so that x0 or y0 = -1 stays >= 0;
        # such entries carry weight 0, wherever they land
        base = row * nb + x0 * BINS + y0 + (BINS + 1)
        acc = np.zeros(b * nb + 2 * (BINS + 1))
        for offset, g in corners:
            acc += np.bincount(base + offset, g * scale, minlength=len(acc))
        out[s : s + b] = acc[BINS + 1 : BINS + 1 + b * nb].reshape(b, nb)
    return out


def _kernel(d: np.ndarray) -> np.ndarray:
    return np.exp(-(d * d) / np.float32(_KERNEL_DIV))


def _columns() -> list[str]:
    return [f"SI beta{i} alpha{j}" for i in range(BINS) for j in range(BINS)]


@register("spin_images", dim=100, columns=_columns())
def spin_images(
    V: np.ndarray, F: np.ndarray, *, n_samples: int = 1024, support: float = 2.0, normals: str = "vertex"
) -> np.ndarray:
    """Spin images, 100 columns = 10 β bins × 10 α bins (column "SI beta{i} alpha{j}").

    Units: the mesh is centred and scaled by `geometry.kalogerakis_units`, and the image covers
    β ∈ [−support, support] (10 bins of support/5, bin 0 at +support: points above the face
    first) and α ∈ [0, support] (10 bins of support/10). Face centre p and normal n as in
    `shape_diameter` (`normals`="vertex": the sum of the vertex normals, as the original). The
    points are the mesh's vertices, weighted by their share of summed face area, or
    `n_samples` of them standing for all when there are more (see `spin_samples`). A point
    counts if its vertex normal faces the same side as n, and spreads its weight over the ≤ 4
    nearest bins with a Gaussian normalised to 1 (`spin_histograms`). So a row sums to the area
    share of the front-facing surface within the support: at most 1 (≈ 0.5 on a sphere). No
    further normalisation.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    centre, unit = kalogerakis_units(V, F)
    V = (V - centre) / unit
    vn = vertex_normals(V, F)
    n = face_normals(V, F, normals, vn)
    P, PN, W = spin_samples(V, vn, vertex_area_weights(V, F), n_samples, support / BINS)
    return spin_histograms(face_centers(V, F), n, P, PN, W, support).astype(np.float32)
