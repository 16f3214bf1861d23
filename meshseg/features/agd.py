"""Average geodesic distance: Kalogerakis et al. 2010's area-weighted statistics of the geodesic
distances from each face to the whole surface (`agd`, 15 columns), and the sampled geodesic
distances that it shares with the geodesic shape context (`shape_context.py`).

All-pairs geodesics are out of reach at 55k faces, so distances are exact Dijkstra distances over
the face dual graph (`geometry.face_dual_graph`) from `n_samples` source faces spread by
farthest-point sampling; every face then stands for the area of its geodesic Voronoi cell (the
faces nearer to its sample than to any other), so sums over the faces of the mesh become sums over
the samples. `sampled_geodesics` is a pure function; `agd` and `shape_context` take the distances
from the mesh's shared `operators.MeshOperators` (argument `ops`), which runs Dijkstra once per
mesh and `n_samples` for both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse.csgraph import connected_components, dijkstra
from threadpoolctl import threadpool_limits

from meshseg.features.geometry import (
    face_areas,
    face_centers,
    face_dual_graph,
    farthest_point_sampling,
    kalogerakis_units,
    per_face_normals,
)
from meshseg.features.registry import register

AGD_COLUMNS = [
    "AGD E[g]",
    "AGD E[g^2]",
    "AGD E[g^4]",
    "AGD E[g^8]",
    "AGD E[g^.5]",
    "AGD E[g^.25]",
    "AGD var",
    "AGD skew",
    "AGD kurt",
    "AGD g@10%",
    "AGD g@20%",
    "AGD g@30%",
    "AGD g@40%",
    "AGD g@50%",
    "AGD unused(0)",
]
_QUANTILES = (0.1, 0.2, 0.3, 0.4, 0.5)
_EPS = 1e-30  # the 2010 code's guard in skewness and kurtosis
_CHUNK = 1024  # faces per block of the (faces x samples) work: bounds memory on large meshes


@dataclass(frozen=True)
class SampledGeodesics:
    """Geodesic distances from sample faces to every face, in the 2010 code's units
    (`geometry.kalogerakis_units`).

    dist[s, f] is the dual-graph distance from face samples[s] to face f (inf across components);
    owner[f] is the sample nearest to f and cell_area[s] the area fraction of its Voronoi cell.
    """

    vertices: np.ndarray  # (V, 3) normalised vertices
    unit: float  # the length, in input units, of one normalised unit
    centers: np.ndarray  # (F, 3) face centres
    normals: np.ndarray  # (F, 3) unit face normals (0 for zero-area faces)
    area: np.ndarray  # (F,) face area / total area
    graph: object  # (F, F) csr dual graph
    component: np.ndarray  # (F,) connected component of each face
    samples: np.ndarray  # (S,) sample face indices
    dist: np.ndarray  # (S, F) float32
    owner: np.ndarray  # (F,) index into samples
    owner_dist: np.ndarray  # (F,) distance from each face to its sample
    cell_area: np.ndarray  # (S,)


def spread_samples(centers: np.ndarray, component: np.ndarray, k: int) -> np.ndarray:
    """`k` faces by farthest-point sampling of the face centres, plus, for every connected component
    left without one, its face nearest to the component's centroid (so that every face reaches a
    sample). The choice depends on the geometry only."""
    samples = farthest_point_sampling(centers, min(k, len(centers)))
    missing = np.setdiff1d(np.unique(component), component[samples])
    if len(missing):
        extra = []
        for c in missing:  # one per component without a sample: few in practice
            members = np.flatnonzero(component == c)
            p = centers[members]
            extra.append(members[np.argmin(((p - p.mean(0)) ** 2).sum(1))])
        samples = np.r_[samples, extra]
    return samples


def sampled_geodesics(V: np.ndarray, F: np.ndarray, n_samples: int) -> SampledGeodesics:
    """Distances from `n_samples` farthest-point sample faces to all faces, with their Voronoi cells.

    Not memoised: `MeshOperators.geodesics` is, per mesh, so that `agd` and `shape_context` run
    Dijkstra once per mesh.
    """
    centre, unit = kalogerakis_units(V, F)
    Vn = (V - centre) / unit
    A = face_areas(Vn, F)
    total = A.sum()
    area = A / total if total > 0 else np.full(len(F), 1.0 / len(F))
    C = face_centers(Vn, F)
    graph = face_dual_graph(Vn, F)
    _, component = connected_components(graph, directed=False)
    samples = spread_samples(C, component, int(n_samples))
    dist = dijkstra(graph, directed=False, indices=samples).astype(np.float32)
    owner = np.argmin(dist, axis=0)  # every face reaches the sample of its own component
    owner_dist = dist[owner, np.arange(len(F))]
    cell_area = np.bincount(owner, weights=area, minlength=len(samples))
    geo = SampledGeodesics(
        Vn, unit, C, per_face_normals(Vn, F), area, graph, component, samples, dist, owner, owner_dist, cell_area
    )
    return geo


def shared_geodesics(V: np.ndarray, F: np.ndarray, n_samples: int, ops) -> SampledGeodesics:
    """The distances from the mesh's shared operators, or computed here when called without them."""
    return sampled_geodesics(V, F, n_samples) if ops is None else ops.geodesics(n_samples)


def spread_quantiles(d: np.ndarray, h: np.ndarray, w: np.ndarray, qs) -> np.ndarray:
    """Per row of (n, S) distances `d` (inf: unreachable), half-widths `h` (> 0) and weights `w`
    (rows summing to 1): the distance within which a fraction q of the weight lies, for each q,
    each sample's weight being spread uniformly over [max(d - h, 0), d + h] (its cell's faces lie
    around it, not all at d). (n, len(qs)).

    The cumulative weight is piecewise linear with breakpoints at the interval ends: sort them,
    integrate the slope between them, and interpolate within the segment that crosses q."""
    n, S = d.shape
    reach = np.isfinite(d)
    d = np.where(reach, d, 0.0)
    lo = np.maximum(d - h, 0.0)
    hi = d + h
    both = np.empty((n, 2 * S))
    both[:, :S] = np.where(reach, lo, np.inf)
    both[:, S:] = np.where(reach, hi, np.inf)
    # row-wise argsort by one integer sort: the float32 bit pattern (monotonic for x >= 0) in the
    # high half of an int64, the column in the low half (several times faster than np.argsort)
    key = both.astype(np.float32).view(np.int32).astype(np.int64)
    key <<= 32
    key |= np.arange(2 * S, dtype=np.int64)
    key.sort(axis=1)
    order = key & 0xFFFFFFFF
    x = np.take_along_axis(both, order, axis=1)
    slope = np.where(reach, w, 0.0) / (hi - lo)
    ds = np.take_along_axis(np.concatenate([slope, -slope], axis=1), order, axis=1)
    s = np.cumsum(ds, axis=1)  # slope after each breakpoint
    with np.errstate(invalid="ignore"):  # inf - inf between unreachable samples
        gap = np.diff(x, axis=1)
    gap[~np.isfinite(gap)] = 0.0
    gap *= s[:, :-1]
    cum = np.zeros((n, 2 * S))  # weight below each breakpoint
    np.cumsum(gap, axis=1, out=cum[:, 1:])
    out = np.empty((n, len(qs)))
    rows = np.arange(n)
    for j, q in enumerate(qs):
        k = np.clip((cum < q).sum(axis=1) - 1, 0, 2 * S - 1)  # last breakpoint below q
        out[:, j] = x[rows, k] + (q - cum[rows, k]) / np.maximum(s[rows, k], 1e-300)
        out[:, j] = np.minimum(out[:, j], x[rows, np.minimum(k + 1, 2 * S - 1)])
    return out


def distance_statistics(geo: SampledGeodesics) -> np.ndarray:
    """The 15 AGD values of every face before the per-mesh shift, in normalised units (F, 15)."""
    nf = len(geo.owner)
    X = np.zeros((nf, 15))
    w_all = geo.cell_area
    # a cell's distances seen from afar spread with variance E[dist to its sample^2] / 2 (a disk);
    # a uniform spread with that variance has half-width sqrt(3) sigma
    sigma2 = np.bincount(geo.owner, geo.area * geo.owner_dist.astype(np.float64) ** 2, len(w_all))
    h = np.sqrt(3.0 * sigma2 / np.maximum(w_all, 1e-300) / 2.0)
    # a cell of one face (or all at its sample) is a narrow interval, not a point: the breakpoints'
    # float32 sort keys must keep its ends apart
    reach = np.isfinite(geo.dist)
    size = max(float(np.median(h)), 1e-3 * float(geo.dist[reach].max(initial=0.0)), 1e-30)
    h = np.maximum(h, 1e-6 * size)[None, :]
    with threadpool_limits(limits=1, user_api="blas"):  # small products: threads only add overhead
        for lo in range(0, nf, _CHUNK):
            rows = slice(lo, min(lo + _CHUNK, nf))
            d = geo.dist[:, rows].T.astype(np.float64)  # (n, S)
            reach = np.isfinite(d)
            d[~reach] = 0.0  # and no weight: statistics over the reachable area only
            total = np.maximum(reach @ w_all, 1e-300)  # 0 only on a component of zero area
            d2 = d * d
            d4 = d2 * d2
            sq = np.sqrt(d)
            # raw moments E[g^p], p = 1, 2, 4, 8, 1/2, 1/4 (the columns) and 3 (for the skewness)
            m = np.stack([x @ w_all for x in (d, d2, d4, d4 * d4, sq, np.sqrt(sq), d2 * d)], axis=1) / total[:, None]
            X[rows, :6] = m[:, :6]
            mu, m2, m3, m4 = m[:, 0], m[:, 1], m[:, 6], m[:, 2]
            var = m2 - mu**2
            X[rows, 6] = var
            X[rows, 7] = (m3 - 3 * mu * m2 + 2 * mu**3) / np.sqrt(var**3 + _EPS)
            X[rows, 8] = (m4 - 4 * mu * m3 + 6 * mu**2 * m2 - 3 * mu**4) / (var**2 + _EPS)
            w = np.where(reach, w_all[None, :], 0.0) / total[:, None]
            X[rows, 9:14] = spread_quantiles(np.where(reach, d, np.inf), h, w, _QUANTILES)
            X[rows, 9:14][w.sum(axis=1) < 0.5] = 0.0  # no area to take quantiles of
    return X


@register("agd", 15, version="1", columns=AGD_COLUMNS, shared=True)
def average_geodesic_distance(V: np.ndarray, F: np.ndarray, *, n_samples: int = 256, ops=None) -> np.ndarray:
    """Area-weighted statistics of the geodesic distances g from a face to the surface (15 columns).

    Columns: E[g], E[g^2], E[g^4], E[g^8], E[g^.5], E[g^.25]; the variance, skewness and kurtosis
    of g; the distances within which 10, 20, 30, 40 and 50 % of the area lies; and a column that is
    always 0 (the 2010 code leaves its 15th value unused).

    Units and normalisation as in the 2010 code: g over the face dual graph, in the units of
    `geometry.kalogerakis_units` (vertices centred on the area-weighted centroid and divided by
    1.5 x the 33rd percentile of the face centres' distances to it), expectations over area
    fractions, and finally each column shifted so that its minimum over the mesh is 0.

    Sampling (`n_samples` Dijkstra sources, shared with `shape_context`): the faces of a sample's
    Voronoi cell are taken at the sample's distance for the moments, and spread uniformly around
    it (with the cell's radial variance) for the quantiles. On a mesh of several components the
    statistics are over the face's own component (area renormalised to 1): the original would sum
    infinite distances.
    """
    X = distance_statistics(shared_geodesics(V, F, n_samples, ops))
    X -= X.min(axis=0)  # the original's per-mesh shift (column 15 stays 0)
    return X.astype(np.float32)
