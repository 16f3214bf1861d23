"""PCA features: Kalogerakis et al. 2010's multi-scale eigenvalues of the covariance of the face
centres in a geodesic neighbourhood (`pca`, 48 columns)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from meshseg.errors import ConfigError
from meshseg.features.geometry import (
    clip_outliers,
    face_areas,
    face_centers,
    face_dual_graph,
    farthest_point_sampling,
    kalogerakis_normalize,
)
from meshseg.features.neighbourhoods import face_neighbours, geodesic_balls
from meshseg.features.registry import register

PCA_VALUES = (
    "l0",
    "l1",
    "l2",
    "l0+l1",
    "l0+l2",
    "l1+l2",
    "l0/l1",
    "l0/l2",
    "l1/l2",
    "l0/l1+l0/l2",
    "l0/l1+l1/l2",
    "l0/l2+l1/l2",
)
PCA_COLUMNS = [f"PCA s{s} {v}" for s in range(4) for v in PCA_VALUES]
_UPPER = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
_SITE_BATCH = 64  # sites per batch of truncated Dijkstra runs in `site_ball_moments`


@dataclass(frozen=True)
class PCASettings:
    """The `pca` group's parameters (see `pca`)."""

    radii: tuple = (0.06, 0.12, 0.30, 0.60)
    max_neighbors: int = 384
    min_faces: int = 9
    site_radius: float = 0.25
    site_spacing: float = 0.2
    site_neighbors: int = 4
    clip: bool = True


class _FaceGraph(NamedTuple):
    """The dual graph Dijkstra runs on (sparse, F x F), each face's edge-adjacent faces ((F, 3), F where
    none) and the face centres."""

    graph: sp.csr_matrix
    nbr: np.ndarray
    centres: np.ndarray


def area_moments(c: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(F, 10) per-face moments [a, a c (3), a c_i c_j (6, upper triangle)]: sums of these over a
    neighbourhood give its area, first and second moments."""
    outer = np.stack([c[:, i] * c[:, j] for i, j in _UPPER], axis=1)
    return np.hstack([a[:, None], a[:, None] * c, a[:, None] * outer])


def covariance_eigenvalues(S: np.ndarray, total_area: float) -> np.ndarray:
    """(..., 10) neighbourhood moment sums -> (..., 3) sqrt eigenvalues l0 <= l1 <= l2 of the 2010
    code's covariance: (1/A) sum_j a_j (c_j - m)(c_j - m)^T with m = (1/A) sum_j a_j c_j, where A is
    the area of the WHOLE mesh (not of the neighbourhood), as in the original. With centres about
    the mesh centroid this mixes the neighbourhood's spread with its position and area."""
    s0, s1 = S[..., 0], S[..., 1:4]
    S2 = np.empty(S.shape[:-1] + (3, 3))
    for q, (i, j) in enumerate(_UPPER):
        S2[..., i, j] = S2[..., j, i] = S[..., 4 + q]
    m = s1 / total_area
    C = (
        S2
        - s1[..., :, None] * m[..., None, :]
        - m[..., :, None] * s1[..., None, :]
        + s0[..., None, None] * m[..., :, None] * m[..., None, :]
    )
    return np.sqrt(np.maximum(np.linalg.eigvalsh(C / total_area), 0.0))


def pca_values(e: np.ndarray) -> np.ndarray:
    """The 12 per-scale values from (..., 3) sqrt eigenvalues: l0, l1, l2, the pair sums, the
    ratios l0/l1, l0/l2, l1/l2 and their pair sums (the original's 1e-30 guards the ratios)."""
    l0, l1, l2 = e[..., 0], e[..., 1], e[..., 2]
    r01, r02, r12 = l0 / (l1 + 1e-30), l0 / (l2 + 1e-30), l1 / (l2 + 1e-30)
    return np.stack([l0, l1, l2, l0 + l1, l0 + l2, l1 + l2, r01, r02, r12, r01 + r02, r01 + r12, r02 + r12], axis=-1)


def site_ball_moments(V: np.ndarray, F: np.ndarray, G: np.ndarray, radii, *, spacing: float, neighbors: int = 4):
    """(F, len(radii), q) sums of the per-face rows G over each face's geodesic ball (plus the ring
    beyond it), for radii at which a ball holds hundreds to thousands of faces.

    Per radius r the sums are exact at M sites, the farthest-point samples of the face centres
    spaced about `spacing` x r (M = mesh area / (spacing r)^2; the samples of a larger radius are
    a prefix of those of a smaller one): one Dijkstra per site over the dual graph. A face then
    takes the inverse-squared-distance mean of the sums of its `neighbors` geodesically nearest
    sites (among its geodesically nearest site and its 2 x `neighbors` Euclidean-nearest ones):
    a ball moves little over one site spacing, so the sums vary smoothly between sites.
    """
    nf = len(F)
    c = face_centers(V, F)
    area = face_areas(V, F).sum()
    radii = [float(r) for r in radii]
    nbr = face_neighbours(V, F).ids
    mesh = _FaceGraph(face_dual_graph(V, F), np.where(nbr < 0, nf, nbr), c)
    counts = [int(np.clip(np.ceil(area / (spacing * r) ** 2), 1, nf)) for r in radii]
    # one FPS order serves every radius (a prefix of it is the FPS of that size); a radius that
    # needs as many sites as faces takes every face
    fps = farthest_point_sampling(c, max([m for m in counts if m < nf], default=1))
    out = np.empty((nf, len(radii), G.shape[1]))
    for i, (r, m) in enumerate(zip(radii, counts)):
        sites = np.arange(nf) if m >= nf else fps[:m]
        out[:, i] = _site_sums(mesh, G, sites, r, spacing * r, neighbors)
    return out


def _site_sums(mesh: _FaceGraph, G, sites, radius, h, neighbors):
    graph, nbr, c = mesh
    batch = _SITE_BATCH
    nf = len(c)
    while True:  # a part that no site reaches (a small component FPS skipped) gets its own site
        d1, _, nearest = dijkstra(
            graph, directed=False, indices=sites, limit=radius, min_only=True, return_predecessors=True
        )
        lost = np.flatnonzero(~np.isfinite(d1))
        if len(lost) == 0:
            break
        gap, _ = cKDTree(c[sites]).query(c[lost])
        sites = np.append(sites, lost[np.argmax(gap)])  # FPS continued over the uncovered faces
    m = len(sites)
    site_index = np.full(nf, -1, np.int64)
    site_index[sites] = np.arange(m)
    # candidate sites per face: its geodesically nearest one and its Euclidean-nearest ones
    ke = min(m, 2 * max(1, int(neighbors)))
    _, cand = cKDTree(c[sites]).query(c, k=ke)
    cand = np.hstack([site_index[nearest][:, None], cand.reshape(nf, ke)])
    cand_d = np.full(cand.shape, np.inf)
    by_site = np.argsort(cand.ravel(), kind="stable")
    bounds = np.searchsorted(cand.ravel()[by_site], np.arange(0, m + batch, batch))

    # float32 sums are ample here: the smallest eigenvalues at these radii sit far above their noise
    G32 = G.astype(np.float32)
    sums = np.empty((m, G.shape[1]))
    inside = np.zeros((min(batch, m), nf + 1), bool)
    for start in range(0, m, batch):
        chunk = sites[start : start + batch]
        b = len(chunk)
        D = dijkstra(graph, directed=False, indices=chunk, limit=radius)
        np.isfinite(D, out=inside[:b, :nf])  # the limit leaves inf beyond the radius
        # a face is taken if it or an edge-adjacent face is within the radius
        taken = inside[:b, :nf] | np.take(inside[:b], nbr[:, 0], axis=1)
        taken |= np.take(inside[:b], nbr[:, 1], axis=1)
        taken |= np.take(inside[:b], nbr[:, 2], axis=1)
        sums[start : start + b] = np.dot(taken.astype(np.float32), G32)  # (np.matmul is 20x slower here)
        sel = by_site[bounds[start // batch] : bounds[start // batch + 1]]
        cand_d.ravel()[sel] = D[cand.ravel()[sel] - start, sel // cand.shape[1]]
    # the nearest site is usually also a Euclidean candidate: count it once
    cand_d[:, 1:][cand[:, 1:] == cand[:, :1]] = np.inf
    k = max(1, min(int(neighbors), cand.shape[1]))
    top = np.argpartition(cand_d, k - 1, axis=1)[:, :k]
    dk = np.take_along_axis(cand_d, top, axis=1)
    w = np.where(np.isfinite(dk), 1.0 / (dk + 1e-3 * h) ** 2, 0.0)
    w /= w.sum(axis=1, keepdims=True)
    return np.einsum("fk,fkq->fq", w, sums[np.take_along_axis(cand, top, axis=1)])


def neighbourhood_moments(V: np.ndarray, F: np.ndarray, G: np.ndarray, settings: PCASettings) -> np.ndarray:
    """(F, len(radii), q) sums of the per-face rows G over each face's neighbourhood: per face
    (`geodesic_balls`) below `site_radius`, through sites (`site_ball_moments`) from it on."""
    radii, s = settings.radii, settings
    small = [i for i, r in enumerate(radii) if r < s.site_radius]
    large = [i for i, r in enumerate(radii) if r >= s.site_radius]
    S = np.zeros((len(F), len(radii), G.shape[1]))
    if small:
        c = face_centers(V, F)
        for rows, J, masks in geodesic_balls(
            c, face_neighbours(V, F), [radii[i] for i in small], max_neighbors=s.max_neighbors, min_faces=s.min_faces
        ):
            GJ = G[J]
            for i, mask in zip(small, masks):
                S[rows, i] = np.einsum("bk,bkq->bq", mask.astype(np.float64), GJ)
    if large:
        S[:, large] = site_ball_moments(
            V, F, G, [radii[i] for i in large], spacing=s.site_spacing, neighbors=s.site_neighbors
        )
    return S


@register("pca", 48, version="1", columns=PCA_COLUMNS, settings=PCASettings)
def pca(V: np.ndarray, F: np.ndarray, settings: PCASettings | None = None) -> np.ndarray:
    """Kalogerakis et al. 2010 PCA features, 12 columns per radius (columns.txt 64-111).

    Per radius (geodesic, in `kalogerakis_normalize` units): the square roots l0 <= l1 <= l2 of
    the eigenvalues of the area-weighted covariance of the face centres in the face's geodesic
    neighbourhood (`covariance_eigenvalues`, with the original's whole-mesh-area normalisation),
    l0, l1, l2, l0+l1, l0+l2, l1+l2, l0/l1, l0/l2, l1/l2, l0/l1+l0/l2, l0/l1+l1/l2, l0/l2+l1/l2.
    Per mesh and column, values are clipped at the 95 % order statistic. Neighbourhoods: radii
    below `site_radius` use `geodesic_balls` per face (at most `max_neighbors` faces, the first
    `min_faces` always taken); larger radii use `site_ball_moments` (exact at FPS sites spaced
    `site_spacing` x radius, interpolated from `site_neighbors` sites). Per face, no vertex mapping.
    """
    s = settings or PCASettings()
    if len(s.radii) != 4:
        raise ConfigError(f"pca: needs 4 radii (the group has 4 x 12 columns), got {list(s.radii)}")
    Vn = kalogerakis_normalize(V, F)
    c = face_centers(Vn, F)
    a = face_areas(Vn, F)
    total = a.sum()
    if not total > 0:
        return np.zeros((len(F), 12 * len(s.radii)), np.float32)
    s = dataclasses.replace(s, radii=[float(r) for r in s.radii])
    with threadpool_limits(limits=1, user_api="blas"):  # many small BLAS calls: threads only add sync overhead
        S = neighbourhood_moments(Vn, F, area_moments(c, a), s)
    X = pca_values(covariance_eigenvalues(S, total)).reshape(len(F), -1)
    if s.clip:
        X = clip_outliers(X, np.zeros(X.shape[1], bool))
    return X.astype(np.float32)
