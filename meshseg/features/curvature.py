"""Curvature features: Kalogerakis et al. 2010's multi-scale quadric-fit curvatures (`curvature`,
64 columns) and pointwise Gaussian curvature (`gc`, 1 column).

Also home of the 2010 code's face neighbourhoods, shared with `pca`: `dual_edges` (its face
graph) and `geodesic_balls` (its geodesic face neighbourhoods, found in batches without a Dijkstra
per face). Its units and face normals are `geometry.kalogerakis_normalize` and
`geometry.smoothed_face_normals`.
"""

from __future__ import annotations

import igl
import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from meshseg.errors import ConfigError
from meshseg.features.geometry import (  # noqa: F401
    edge_face_pairs,
    face_areas,
    face_centers,
    kalogerakis_normalize,
    per_face_normals,
    smoothed_face_normals,
    vertex_to_face,
)
from meshseg.features.registry import register

CURVATURE_VALUES = ("k1", "k2", "k1-k2", "K1", "K2", "K1-K2", "H", "K")
CURVATURE_COLUMNS = [
    f"CUR s{s} {v}" for s in range(4) for v in CURVATURE_VALUES + tuple(f"|{v}|" for v in CURVATURE_VALUES)
]


# ---------------------------------------------------------------------------------------------
# shared operators


def dual_edges(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each face's edge-adjacent faces and the dual edge lengths (centre -> shared edge midpoint ->
    centre, as `face_dual_graph`): ((F, 3) face ids, -1 where none; (F, 3) lengths, inf where none).
    On a non-manifold edge the nearest three neighbours are kept, as the 2010 code keeps one face
    per edge."""
    nf = len(F)
    pairs, shared = edge_face_pairs(F)
    c = face_centers(V, F)
    mid = V[shared].mean(axis=1)
    w = np.linalg.norm(c[pairs[:, 0]] - mid, axis=1) + np.linalg.norm(mid - c[pairs[:, 1]], axis=1)
    src = np.r_[pairs[:, 0], pairs[:, 1]]
    dst = np.r_[pairs[:, 1], pairs[:, 0]]
    w = np.r_[w, w]
    order = np.lexsort((w, src))
    src, dst, w = src[order], dst[order], w[order]
    rank = np.arange(len(src)) - np.searchsorted(src, src)
    keep = rank < 3
    nbr = np.full((nf, 3), -1, np.int64)
    length = np.full((nf, 3), np.inf)
    nbr[src[keep], rank[keep]] = dst[keep]
    length[src[keep], rank[keep]] = w[keep]
    return nbr, length


def geodesic_balls(
    c: np.ndarray,
    nbr: np.ndarray,
    nbr_len: np.ndarray,
    radii,
    *,
    max_neighbors: int,
    min_faces: int = 0,
    normals: np.ndarray | None = None,
    table_entries: int = 1 << 24,
    work_entries: int = 1 << 18,
):
    """The 2010 code's geodesic face neighbourhoods, for every face, in batches.

    Its traversal is a Dijkstra over the dual graph (`dual_edges`) from the face: a face is taken
    when popped, expanded while its distance is <= radius, so the neighbourhood is the geodesic ball
    plus one ring beyond it; the first `min_faces` popped faces are taken (and expanded) whatever
    their distance, and with `normals` a face whose normal points away from the source's
    (dot <= 0) is neither taken nor expanded.

    Here the candidates of each face are its nearest face centres within the largest radius plus
    one dual edge (a KD-tree query: a geodesic ball lies inside the Euclidean ball of the same
    radius), at most `max_neighbors` of them, and the graph distances inside that candidate set
    come from a batched Bellman-Ford relaxation, one sweep per ring, run once at the largest
    radius. Exact unless a ball holds more than `max_neighbors` faces (then it is cut to the
    nearest ones, i.e. its radius shrinks). Memory is bounded by `table_entries` (a per-batch
    face -> slot table) and `work_entries` (batch rows x candidates x 3).

    Yields (rows (B,), J (B, K) candidate face ids with J[:, 0] = rows, [mask (B, K) bool per radius]).
    """
    c = np.asarray(c, dtype=np.float64)
    nf = len(c)
    radii = [float(r) for r in radii]
    finite_len = nbr_len[np.isfinite(nbr_len)]
    # a ring face lies at most one dual edge beyond the ball
    margin = float(np.percentile(finite_len, 95)) if len(finite_len) else 0.0
    reach = max(radii) + margin
    tree = cKDTree(c)
    cap = max(int(max_neighbors), min_faces + 2)
    # batch faces of similar candidate counts together
    count = np.minimum(tree.query_ball_point(c, reach, return_length=True), cap)
    order = np.argsort(count, kind="stable")
    nbr_pad = np.vstack([np.where(nbr < 0, nf, nbr), np.full((1, 3), nf)])  # row nf: padding face
    len_pad = np.vstack([nbr_len, np.full((1, 3), np.inf)])
    rows_per_table = max(1, min(nf, table_entries // (nf + 1), work_entries // (3 * min(cap, 16))))
    table = np.full(rows_per_table * (nf + 1), -1, np.int32)  # per row: face id -> candidate slot
    start = 0
    while start < nf:
        b = max(1, min(rows_per_table, work_entries // (3 * max(1, count[order[start]]))))
        rows = order[start : start + b]
        start += len(rows)
        J = _nearest(tree, c, rows, max(1, min(int(count[rows].max()), nf)), reach)
        B, k = J.shape
        r_idx = np.arange(B)[:, None]
        at = J + (nf + 1) * r_idx  # flat positions in the slot table
        table[at] = np.arange(k, dtype=np.int32)[None, :]
        table[(nf + 1) * np.arange(B) + nf] = -1
        slot = np.take(table, nbr_pad[J] + (nf + 1) * r_idx[:, :, None])  # (B, k, 3): candidate slot of each neighbour
        table[at] = -1
        compat = None if normals is None else np.einsum("bkj,bj->bk", normals[np.minimum(J, nf - 1)], normals[rows]) > 0
        # edge-major gather indices into a (B, k + 1) array whose last column is a sentinel
        flat = np.where(slot >= 0, slot, k) + (k + 1) * r_idx[:, :, None]
        flat = np.ascontiguousarray(np.moveaxis(flat, 2, 0))
        wlen = np.ascontiguousarray(np.moveaxis(len_pad[J], 2, 0))  # (3, B, k) dual edge lengths
        # one relaxation at the largest radius: shortest paths to faces inside a smaller ball stay
        # inside it, so each smaller neighbourhood follows from the same distances
        if compat is None and min_faces > 0:
            # without the normal test the forced first faces only matter where fewer than
            # min_faces + 1 faces lie in the smallest ball: relax those rows again with them
            dist, t_exp, t_inc = _relax(flat, wlen, None, max(radii), 0)
            few = np.flatnonzero((dist <= min(radii)).sum(axis=1) < min_faces + 1)
            if len(few):
                local = flat[:, few] % (k + 1) + (k + 1) * np.arange(len(few))[None, :, None]
                d2, e2, i2 = _relax(local, wlen[:, few], None, max(radii), min_faces)
                dist[few], t_exp, t_inc = d2, np.full((B, 1), -np.inf), np.full((B, 1), -np.inf)
                t_exp[few], t_inc[few] = e2, i2
        else:
            dist, t_exp, t_inc = _relax(flat, wlen, compat, max(radii), min_faces)
        masks = [_taken(dist, flat, compat, R, t_exp, t_inc) for R in radii]
        J = np.where(J < nf, J, rows[:, None])  # padding -> the face itself, never in a mask
        yield rows, J, masks


def _nearest(tree, c, rows, k, reach):
    """(B, K) face ids of the k nearest centres within `reach` of each row's centre, nearest
    first and the face itself in column 0, padded with nf; K is the largest count found."""
    d, J = tree.query(c[rows], k=k, distance_upper_bound=reach)
    J = J.reshape(len(rows), k)
    width = int(np.isfinite(d.reshape(len(rows), k)).sum(axis=1).max())
    J = J[:, : max(width, 1)]
    is_self = J == rows[:, None]
    missing = ~is_self.any(axis=1)  # coincident centres can crowd the face out of its own list
    J[missing, -1] = rows[missing]
    is_self[missing, -1] = True
    first = np.argmax(is_self, axis=1)
    J[np.arange(len(rows)), first] = J[:, 0]
    J[:, 0] = rows
    return J


def _relax(flat, wlen, compat, R, min_faces):
    """Bellman-Ford from slot 0 over the candidate slots, one sweep per ring, expanding a face
    while its distance is <= R (and its normal is compatible) or it is among the first
    `min_faces` popped. Returns distances (B, k) and the distances of the (min_faces - 1)-th and
    min_faces-th nearest faces (the forced expansion / forced take thresholds, (B, 1) each)."""
    _, B, k = flat.shape
    dist = np.full((B, k + 1), np.inf)
    dist[:, 0] = 0.0
    de = np.full((B, k + 1), np.inf)  # distances of expanded faces, inf elsewhere
    t_exp = t_inc = np.full((B, 1), -np.inf)
    for it in range(k + 1):
        dd = dist[:, :k]
        if min_faces > 0 and it <= min_faces + 1:
            # the m nearest faces are final after m sweeps (their paths run through nearer ones)
            t_exp, t_inc = _forced(dd, min_faces)
        expand = dd <= R
        if compat is not None:
            expand &= compat | (dd <= t_inc)  # a forced-taken face expands like any other
        expand |= dd <= t_exp
        np.copyto(de[:, :k], np.where(expand, dd, np.inf))
        p = np.take(de, flat)
        p += wlen
        new = np.minimum(np.minimum(p[0], p[1]), np.minimum(p[2], dd))
        if np.array_equal(new, dd):
            break
        dist[:, :k] = new
    dd = dist[:, :k]
    if min_faces > 0:
        t_exp, t_inc = _forced(dd, min_faces)
    return dd, t_exp, t_inc


def _forced(dd, min_faces):
    """Distances of the (min_faces-1)-th and min_faces-th nearest faces: the first `min_faces`
    popped are expanded, the first `min_faces` + 1 taken, whatever their distance and normal."""
    k = dd.shape[1]
    m_exp, m_inc = min(min_faces, k) - 1, min(min_faces, k - 1)
    part = np.partition(dd, (m_exp, m_inc) if m_exp != m_inc else m_inc, axis=1)
    return part[:, m_exp : m_exp + 1], part[:, m_inc : m_inc + 1]


def _taken(dist, flat, compat, R, t_exp, t_inc):
    """The neighbourhood of radius R from the distances: the faces a Dijkstra limited to R pops
    (expanded faces and their neighbours), less those with an incompatible normal unless they are
    among the first popped."""
    expanded = dist <= R
    if compat is not None:
        expanded &= compat | (dist <= t_inc)
    expanded |= dist <= t_exp
    B, k = dist.shape
    ex = np.zeros((B, k + 1), bool)
    ex[:, :k] = expanded
    g = np.take(ex, flat)
    taken = expanded | g[0] | g[1] | g[2]
    taken &= np.isfinite(dist)
    if compat is not None:
        taken &= compat | (dist <= t_inc)
    taken[:, 0] = True
    return taken


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
    nbr, nbr_len = dual_edges(V, F)
    out = np.zeros((len(F), len(radii), 2))
    for rows, J, masks in geodesic_balls(
        c, nbr, nbr_len, radii, max_neighbors=max_neighbors, min_faces=min_faces, normals=n
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
        np.multiply(xx, xx, out=Q[..., 0])
        np.multiply(xx, xy, out=Q[..., 1])
        np.multiply(xx, yy, out=Q[..., 2])
        np.multiply(xy, yy, out=Q[..., 3])
        np.multiply(yy, yy, out=Q[..., 4])
        np.multiply(z, xx, out=Q[..., 8])
        np.multiply(z, xy, out=Q[..., 9])
        np.multiply(z, yy, out=Q[..., 10])
        np.multiply(u, x, out=Q[..., 11])
        np.multiply(u, y, out=Q[..., 12])
        np.multiply(v, x, out=Q[..., 13])
        np.multiply(v, y, out=Q[..., 14])
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


@register("curvature", 64, version="1", columns=CURVATURE_COLUMNS)
def curvature(
    V: np.ndarray,
    F: np.ndarray,
    *,
    radii: tuple = (0.01, 0.02, 0.05, 0.10),
    max_neighbors: int = 256,
    min_faces: int = 3,
    smoothed_normals: bool = True,
    clip: bool = True,
    smooth: bool = True,
) -> np.ndarray:
    """Kalogerakis et al. 2010 curvature, 16 columns per radius (columns.txt 0-63).

    Per radius (geodesic, in `kalogerakis_normalize` units, so the columns are scale-invariant):
    k1, k2, k1-k2, K1, K2, K1-K2, H, K and their absolute values (`curvature_values`) from a
    quadric fitted to the face's geodesic neighbourhood (`principal_curvatures`). Per mesh and
    column, values are clipped to the 5-95 % order statistics (absolute columns: to the 95 % one),
    then averaged with the edge-adjacent faces' values, as the original does. Everything is
    per face: no vertex-to-face mapping. `smoothed_normals=False` uses the triangles' own normals
    instead of the original's smoothed ones (`smoothed_face_normals`).
    """
    if len(radii) != 4:
        raise ConfigError(f"curvature: needs 4 radii (the group has 4 x 16 columns), got {list(radii)}")
    Vn = kalogerakis_normalize(V, F)
    with threadpool_limits(limits=1, user_api="blas"):  # many small BLAS calls: threads only add sync overhead
        k = principal_curvatures(
            Vn, F, radii, max_neighbors=max_neighbors, min_faces=min_faces, smoothed_normals=smoothed_normals
        )
    nbr, _ = dual_edges(Vn, F)
    signed = np.arange(16) < 8
    cols = []
    for i in range(len(radii)):
        X = curvature_values(k[:, i, 0], k[:, i, 1])
        if clip:
            X = clip_outliers(X, signed)
        if smooth:
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
