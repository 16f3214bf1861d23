"""The 2010 code's geodesic face neighbourhoods, shared by `curvature` and `pca`: `face_neighbours`
(its face graph) and `geodesic_balls` (its geodesic face neighbourhoods, found in batches without a
Dijkstra per face)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from meshseg.features.geometry import edge_face_pairs, face_centers

# memory bounds of `geodesic_balls`: its per-batch face -> slot table, and batch rows x candidates x 3
_TABLE_ENTRIES = 1 << 24
_WORK_ENTRIES = 1 << 18


class FaceNeighbours(NamedTuple):
    """Each face's edge-adjacent faces, (F, 3) ids (-1 where none), and the dual edge lengths to them,
    (F, 3) (inf where none)."""

    ids: np.ndarray
    lengths: np.ndarray


def face_neighbours(V: np.ndarray, F: np.ndarray) -> FaceNeighbours:
    """Each face's edge-adjacent faces and the dual edge lengths (centre -> shared edge midpoint ->
    centre, as `face_dual_graph`).
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
    return FaceNeighbours(nbr, length)


def geodesic_balls(
    c: np.ndarray,
    neighbours: FaceNeighbours,
    radii,
    *,
    max_neighbors: int,
    min_faces: int = 0,
    normals: np.ndarray | None = None,
):
    """The 2010 code's geodesic face neighbourhoods, for every face, in batches.

    Its traversal is a Dijkstra over the dual graph (`face_neighbours`) from the face: a face is taken
    when popped, expanded while its distance is <= radius, so the neighbourhood is the geodesic ball
    plus one ring beyond it; the first `min_faces` popped faces are taken (and expanded) whatever
    their distance, and with `normals` a face whose normal points away from the source's
    (dot <= 0) is neither taken nor expanded.

    Here the candidates of each face are its nearest face centres within the largest radius plus
    one dual edge (a KD-tree query: a geodesic ball lies inside the Euclidean ball of the same
    radius), at most `max_neighbors` of them, and the graph distances inside that candidate set
    come from a batched Bellman-Ford relaxation, one sweep per ring, run once at the largest
    radius. Exact unless a ball holds more than `max_neighbors` faces (then it is cut to the
    nearest ones, i.e. its radius shrinks). Memory is bounded by `_TABLE_ENTRIES` (a per-batch
    face -> slot table) and `_WORK_ENTRIES` (batch rows x candidates x 3).

    Yields (rows (B,), J (B, K) candidate face ids with J[:, 0] = rows, [mask (B, K) bool per radius]).
    """
    c = np.asarray(c, dtype=np.float64)
    nbr, nbr_len = neighbours
    table_entries, work_entries = _TABLE_ENTRIES, _WORK_ENTRIES
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
