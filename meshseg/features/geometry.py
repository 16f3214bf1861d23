"""Mesh operators shared by the feature families: plain arrays in, plain arrays out.

Faces are the unit of everything downstream, so most operators are per face. Names follow
libigl's where libigl has the operator.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from meshseg.data.mesh import face_areas  # noqa: F401  (re-exported: one definition)


def face_centers(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Centroid of each triangle (F, 3)."""
    return V[F].mean(axis=1)


def per_face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unit normal of each triangle (F, 3); zero for a zero-area face."""
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def _unit(X: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(X, axis=-1, keepdims=True)
    return np.divide(X, norm, out=np.zeros_like(X, dtype=np.float64), where=norm > 0)


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unit vertex normals (V, 3): face cross products weighted at each corner by 1/(|a|²|b|²) of
    the two edges meeting there (Max 1999; TriMesh2, as the 2010 feature code). Zero for a vertex
    no face with area touches."""
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    a, b, c = p0 - p2, p1 - p0, p2 - p1
    la, lb, lc = (np.einsum("ij,ij->i", e, e) for e in (a, b, c))
    fn = np.cross(a, b)
    N = np.zeros_like(V, dtype=np.float64)
    for k, l2 in ((0, la * lb), (1, lb * lc), (2, lc * la)):
        # a zero-length edge gives no direction at that corner: weight 0 instead of inf
        w = np.divide(1.0, l2, out=np.zeros_like(l2), where=l2 > 0)
        for d in range(3):
            N[:, d] += np.bincount(F[:, k], fn[:, d] * w, minlength=len(V))
    return _unit(N)


def smoothed_face_normals(V: np.ndarray, F: np.ndarray, vn: np.ndarray | None = None) -> np.ndarray:
    """The face normal of the 2010 feature code: the normalised sum of the face's three
    `vertex_normals` (not the triangle's own normal); the triangle's normal where that sum
    vanishes; zero where both do (a degenerate face)."""
    vn = vertex_normals(V, F) if vn is None else vn
    n = _unit(vn[F].sum(axis=1))
    bad = ~n.any(axis=1)
    if bad.any():
        n[bad] = per_face_normals(V, F[bad])
    return n


def edge_face_pairs(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of faces sharing an edge, and that edge: ((P, 2) face indices, (P, 2) vertex indices).

    On a non-manifold edge shared by k > 2 faces every pair of them is returned.
    """
    nf = len(F)
    edges = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(nf), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    edges, owner = edges[order], owner[order]
    same = np.all(edges[1:] == edges[:-1], axis=1)
    # runs of equal edges: pair every member with every later member of its run
    starts = np.flatnonzero(np.r_[True, ~same])
    lengths = np.diff(np.r_[starts, len(edges)])
    pairs, shared = [], []
    for k in range(2, lengths.max(initial=1) + 1):
        s = starts[lengths == k]
        for i in range(k):
            for j in range(i + 1, k):
                pairs.append(np.c_[owner[s + i], owner[s + j]])
                shared.append(edges[s])
    if not pairs:
        return np.empty((0, 2), np.int64), np.empty((0, 2), np.int64)
    return np.concatenate(pairs), np.concatenate(shared)


def face_adjacency(F: np.ndarray) -> sp.csr_matrix:
    """Symmetric F x F 0/1 matrix of faces sharing an edge."""
    pairs, _ = edge_face_pairs(F)
    nf = len(F)
    a = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(nf, nf))
    a = (a + a.T).tocsr()
    a.data[:] = 1.0
    return a


def face_dual_graph(V: np.ndarray, F: np.ndarray) -> sp.csr_matrix:
    """Edge-adjacent faces joined with weight = distance between their centroids (path through the
    shared edge's midpoint, so the length follows the surface across creases)."""
    pairs, shared = edge_face_pairs(F)
    c = face_centers(V, F)
    mid = V[shared].mean(axis=1)
    w = np.linalg.norm(c[pairs[:, 0]] - mid, axis=1) + np.linalg.norm(mid - c[pairs[:, 1]], axis=1)
    w = np.maximum(w, 1e-12)  # csgraph treats explicit zeros as missing edges
    nf = len(F)
    g = sp.coo_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(nf, nf))
    return (g + g.T).tocsr()


def geodesic_distances(graph: sp.csr_matrix, sources: np.ndarray, limit: float = np.inf) -> np.ndarray:
    """Shortest-path distances (len(sources), F) over a face graph; inf beyond `limit` or across
    disconnected components."""
    return dijkstra(graph, directed=False, indices=np.asarray(sources), limit=limit)


def vertex_to_face(values: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Per-vertex quantity -> per-face: the mean over the face's three vertices."""
    return values[F].mean(axis=1)


def kalogerakis_units(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre, unit) of the 2010 code's mesh normalisation: the area-weighted centroid of the face
    centres, and (0.5 / 0.33) x the 33rd percentile of the face centres' distances to it (a robust
    "radius" of about 0.5 for a compact shape). Radii of the 593 features are in these units."""
    c, a = face_centers(V, F), face_areas(V, F)
    total = a.sum()
    centre = a @ c / total if total > 0 else c.mean(axis=0)
    r = np.linalg.norm(c - centre, axis=1)
    k = int(0.33 * len(r))
    unit = np.partition(r, k)[k] * (0.5 / 0.33)
    if not unit > 0:  # degenerate input (all centres at one point): keep the units finite
        unit = r.max() if r.max() > 0 else 1.0
    return centre, float(unit)


def kalogerakis_normalize(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Vertices in the 2010 code's units (see `kalogerakis_units`)."""
    centre, unit = kalogerakis_units(V, F)
    return (V - centre) / unit


def farthest_point_sampling(points: np.ndarray, k: int, tie: float = 1e-9) -> np.ndarray:
    """Indices of `k` points spread by Euclidean farthest-point sampling.

    Starts from the point farthest from the centroid, so the choice depends only on the point set:
    invariant to rigid motions and to the order of the points. Distances equal to within a relative
    `tie` count as equal and the lowest index wins: mirror-symmetric meshes (common in L-PSB) have
    exact ties that rounding would otherwise break differently after a rotation. A k-d tree limits
    each update to the points nearer the new sample than the current sampling radius — the only
    ones whose distance can drop.
    """
    from scipy.spatial import cKDTree

    n = len(points)
    if k >= n:
        return np.arange(n)
    chosen = np.empty(k, np.int64)
    centred = points - points.mean(axis=0)
    d = np.einsum("ij,ij->i", centred, centred)
    chosen[0] = np.argmax(d >= d.max() * (1 - tie))
    diff = points - points[chosen[0]]
    d = np.einsum("ij,ij->i", diff, diff)
    tree = cKDTree(points)
    for i in range(1, k):
        chosen[i] = q = np.argmax(d >= d.max() * (1 - tie))
        near = np.asarray(tree.query_ball_point(points[q], np.sqrt(d[q]) * (1 + tie)), dtype=np.int64)
        diff = points[near] - points[q]
        d[near] = np.minimum(d[near], np.einsum("ij,ij->i", diff, diff))
    return chosen


def clip_outliers(X: np.ndarray, signed: np.ndarray) -> np.ndarray:
    """The 2010 code's per-mesh outlier clipping, per column: a `signed` column is clipped to its
    [5 %, 95 %] order statistics, the others (absolute values) to the 95 % order statistic of |x|."""
    X = np.array(X, dtype=np.float64)
    n = len(X)
    hi_i, lo_i = int(0.95 * n), int(0.05 * n)
    for j in range(X.shape[1]):
        if signed[j]:
            s = np.partition(X[:, j], (lo_i, hi_i))
            X[:, j] = np.clip(X[:, j], s[lo_i], s[hi_i])
        else:
            hi = np.partition(np.abs(X[:, j]), hi_i)[hi_i]
            X[:, j] = np.where(np.abs(X[:, j]) < hi, X[:, j], np.sign(X[:, j]) * hi)
    return X
