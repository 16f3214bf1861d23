"""Geodesic shape context: Kalogerakis et al. 2010's histograms of the surface around each face
over geodesic distance and angle (`shape_context`, 270 columns).

For a face i and every other face k the 2010 code takes
  - the geodesic distance d(i, k) over the face dual graph,
  - the angle asin(u . n_k) in [-90, 90] degrees between the direction u from i's centre to k's
    centre and k's tangent plane (positive where k faces away from i, as on a convex surface),
  - the weight (area_k / total area) / (d / D + 0.1), D a per-mesh geodesic scale,
and adds the weight to the bin of (d, angle) in six binnings: 5 or 10 distance bins x 4, 6 or 8
angle bins of equal width. Distance bin x of n spans [e_x, e_{x+1}) with
e_x = 1.2 D (-ln((n + 1 - x) / (n + 1)))^0.9 / ln(n + 1)^0.9: narrow near the face, the last ending
at 1.2 D; farther faces are not counted. The histograms are not normalised: each binning of a face
sums to sum_k (area_k / A) / (d / D + 0.1) over the faces within 1.2 D (about 1.9 on L-PSB shapes).
D, the per-mesh normalisation, is the 95th percentile over source points of the 95th percentile of
their geodesic distances.

Here the distances come from sample faces (`agd.sampled_geodesics`, run once per mesh for both
`agd` and this group by `operators.MeshOperators`), in two levels:
  - far field: `n_samples` farthest-point samples with exact distances to every face. Each stands
    for its geodesic Voronoi cell: the cell's area is spread uniformly over distances d(i, sample)
    -+ sqrt(3) sigma (sigma^2: the cell's mean squared radius / 2) and over u . n values with the
    mean and variance given by the cell's area-weighted normal moments (u towards its centroid);
  - near field: `n_near_samples` finer samples with Dijkstra truncated at the radius that holds
    `near_area` of the surface: for every face the fine cells within that radius replace the
    part of the coarse cells they cover, so the narrow bins near the face see the surface at the
    fine cells' resolution.
With every face a sample, no near field and `soft_binning=False` this is the 2010 definition
exactly (tested).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from threadpoolctl import threadpool_limits

from meshseg.features.agd import shared_geodesics
from meshseg.features.geometry import farthest_point_sampling
from meshseg.features.registry import register

BINNINGS = ((5, 4), (5, 6), (5, 8), (10, 4), (10, 6), (10, 8))
SC_COLUMNS = [
    f"SC b{b}({nd}x{na}) d{x} a{y}" for b, (nd, na) in enumerate(BINNINGS) for x in range(nd) for y in range(na)
]
MAX_DISTANCE = 1.2  # last distance edge, in units of the mesh scale D
LOG_POWER = 0.9  # exponent of the log-spaced distance edges
WEIGHT_OFFSET = 0.1  # weight 1 / (d / D + 0.1)
_CHUNK = 256  # faces per block of the (faces x cells) work: small blocks stay in cache
_MIN_VAR = 1e-4  # floor of the variance of u . n within a cell (a flat cell)
_BOX = np.sqrt(3.0)  # half-width / sigma of a uniform distribution

# interior angle edges of the three angle binnings, as sines (the histogram is over u . n)
_ANGLE_EDGES = {na: np.sin(np.radians(-90.0 + 180.0 * np.arange(1, na) / na)) for na in (4, 6, 8)}
_SINES = np.unique(np.concatenate(list(_ANGLE_EDGES.values())))


def distance_edges(n_bins: int, max_distance: float) -> np.ndarray:
    """The n_bins + 1 log-spaced distance edges from 0 to `max_distance` (the 2010 code's)."""
    s = n_bins + 1
    x = np.arange(s)
    return (-np.log((s - x) / s)) ** LOG_POWER * (max_distance / np.log(s) ** LOG_POWER)


def geodesic_scale(dist: np.ndarray, counts: np.ndarray, calibration: float) -> float:
    """The mesh scale D: the 95th percentile over sources of each source's 95th-percentile distance
    (over the faces it reaches), sources weighted by the number of faces they stand for.

    The 2010 code takes every vertex (or every few) as a source and measures over the vertex-edge
    graph. Paths over the face dual graph are longer (on a regular triangulation it is a honeycomb)
    and farthest-point sources over-represent the extremities: on L-PSB shapes this estimate is
    1.161 x the original's (sd 0.028 over 54 meshes), which `calibration` removes."""
    per = np.empty(len(dist))
    for s, row in enumerate(dist):  # a few hundred rows
        r = row[np.isfinite(row)]
        k = int(0.95 * (len(r) - 1))
        per[s] = np.partition(r, k)[k]
    order = np.argsort(per)
    cum = np.cumsum(counts[order])
    k = min(np.searchsorted(cum, 0.95 * cum[-1]), len(per) - 1)
    return float(per[order][k]) * calibration


def area_radius(geo, fraction: float) -> float:
    """The geodesic radius around a face that holds `fraction` of the surface area (median over
    the coarse samples, each seeing the cells at their samples' distances)."""
    d = geo.dist[:, geo.samples].astype(np.float64)  # (S, S) sample to sample
    order = np.argsort(d, axis=1)
    cum = np.cumsum(geo.cell_area[order], axis=1)
    k = np.minimum((cum < fraction).sum(axis=1), d.shape[1] - 1)
    return float(np.median(np.take_along_axis(d, order, axis=1)[np.arange(len(d)), k]))


class Cells(NamedTuple):
    """A partition of the faces into geodesic Voronoi cells: each face's cell (F,), the number of cells,
    and each face's distance to its cell's sample (F,)."""

    owner: np.ndarray
    count: int
    dist: np.ndarray


def cell_moments(cells: Cells, area: np.ndarray, centers: np.ndarray, normals: np.ndarray, fallback_centers):
    """Area-weighted statistics of Voronoi cells: area (n,), centroid (n, 3), mean normal (n, 3),
    normal second moment (n, 3, 3) and radial spread sigma (n,) with sigma^2 = E[dist^2] / 2, the
    variance of a disk-like cell's distances seen from afar. `fallback_centers`: the centroids of cells
    without area."""
    owner, n_cells, owner_dist = cells
    w = np.bincount(owner, weights=area, minlength=n_cells)
    safe = np.where(w > 0, w, 1.0)
    cen = np.stack([np.bincount(owner, area * centers[:, j], n_cells) for j in range(3)], 1) / safe[:, None]
    cen[w <= 0] = fallback_centers[w <= 0]
    mn = np.stack([np.bincount(owner, area * normals[:, j], n_cells) for j in range(3)], 1) / safe[:, None]
    nn = np.stack(
        [np.bincount(owner, area * normals[:, j] * normals[:, l], n_cells) for j in range(3) for l in range(3)], 1
    )
    nn = nn.reshape(n_cells, 3, 3) / safe[:, None, None]
    sigma = np.sqrt(np.bincount(owner, area * owner_dist.astype(np.float64) ** 2, n_cells) / safe / 2.0)
    return w, cen, mn, nn, sigma


def _uniform_cdfs(edges: np.ndarray, lo: np.ndarray, hi: np.ndarray, scale=None) -> list:
    """CDF at each edge of uniform distributions on [lo, hi] (n, m), times `scale` (n, m) if given:
    a list of (n, m) float32 arrays, one per edge; lo == hi is a point mass (hard binning)."""
    inv = (1.0 / np.maximum(hi - lo, 1e-12)).astype(np.float32)
    top = 1.0
    if scale is not None:  # clip(x, 0, 1) * w = clip(x * w, 0, w) for w >= 0: one pass fewer per edge
        top = scale.astype(np.float32)
        inv *= top
    off = (lo * inv).astype(np.float32)
    out = []
    for e in edges.astype(np.float32):
        c = e * inv
        c -= off
        out.append(np.clip(c, 0.0, top, out=c))
    return out


class _Histogrammer:
    """Adds cells to the six histograms of a block of faces.

    A cell is a set of faces seen from face i at distance d (spread sigma; its part nearer than
    `lower` counted elsewhere), with weight w and, along the direction u from i to its centroid,
    u . n distributed with mean mu and variance var. Its distances are spread uniformly over
    [max(d - sqrt(3) sigma, lower), max(d, lower) + sqrt(3) sigma] and its u . n uniformly over
    mu -+ sqrt(3) sd (mass beyond +-1 in the end bins): uniform distributions with the cell's
    mean and variance, cheap and with compact support."""

    def __init__(self, dmax: float, soft: bool):
        self.edges = {nd: distance_edges(nd, dmax) for nd in (5, 10)}
        self.all_edges = np.unique(np.concatenate(list(self.edges.values())))
        self.index = {nd: np.searchsorted(self.all_edges, e) for nd, e in self.edges.items()}
        self.soft = soft

    def add(self, H: np.ndarray, d, sigma, lower, w, direction) -> None:
        """H (n, 270) += the cells (n, m) of each row; `direction`: (mu, var) of u . n."""
        mu, var = direction
        n, m = d.shape
        h = _BOX * sigma if self.soft else np.zeros_like(d)
        c = np.maximum(d, lower)
        live = self.all_edges > lower  # the CDF is 0 at edges at or below `lower`
        zero = np.zeros((n, m), np.float32)
        dc = [zero] * int((~live).sum()) + _uniform_cdfs(self.all_edges[live], np.maximum(c - h, lower), c + h, w)
        hs = _BOX * np.sqrt(np.maximum(var, _MIN_VAR)) if self.soft else np.zeros_like(mu)
        ac = dict(zip(_SINES, _uniform_cdfs(_SINES, mu - hs, mu + hs)))
        pd = {}
        for nd, idx in self.index.items():  # weighted distance bins; beyond the last edge: dropped
            p = np.empty((n, nd, m), np.float32)
            for x in range(nd):
                np.subtract(dc[idx[x + 1]], dc[idx[x]], out=p[:, x])
            pd[nd] = p
        pa = {}
        for na, e in _ANGLE_EDGES.items():  # angle bins: mass below -1 / above +1 in the end bins
            p = np.empty((n, m, na), np.float32)
            prev = 0.0
            for y in range(na - 1):
                cur = ac[e[y]]
                p[:, :, y] = cur - prev
                prev = cur
            p[:, :, na - 1] = 1.0 - prev
            pa[na] = p
        col = 0
        for nd, na in BINNINGS:
            H[:, col : col + nd * na] += np.matmul(pd[nd], pa[na]).reshape(n, -1)
            col += nd * na


def _near_pairs(graph, sources: np.ndarray, radius: float, nf: int):
    """(source index, face, distance) for every face within `radius` of each source (truncated
    Dijkstra, sources in batches so that the dense rows stay small)."""
    batch = max(1, int(4e6 // max(nf, 1)))
    src, face, dist = [], [], []
    for lo in range(0, len(sources), batch):
        D = dijkstra(graph, directed=False, indices=sources[lo : lo + batch], limit=radius)
        r, f = np.nonzero(np.isfinite(D))
        src.append(r + lo)
        face.append(f)
        dist.append(D[r, f])
    return np.concatenate(src), np.concatenate(face), np.concatenate(dist)


def _padded(i: np.ndarray, nf: int, *cols):
    """Group pair arrays by face i into (nf, K) arrays padded with zeros (K: most pairs of a face)
    and a (nf, K) mask of real entries."""
    order = np.argsort(i, kind="stable")
    i = i[order]
    counts = np.bincount(i, minlength=nf)
    K = max(int(counts.max(initial=0)), 1)
    start = np.cumsum(counts) - counts
    slot = np.arange(len(i)) - start[i]
    mask = np.zeros((nf, K), bool)
    mask[i, slot] = True
    out = []
    for c in cols:
        x = np.zeros((nf, K) + c.shape[1:], c.dtype)
        x[i, slot] = c[order]
        out.append(x)
    return mask, out


class _FarDirections:
    """mean and variance of u . n from faces to the coarse cells, u the unit direction from the face
    centre to the cell centroid, by matrix products over (faces x cells) instead of per pair:
    r^2 = |c - x|^2, r mu = (c - x) . m, r^2 E[(u . n)^2] = (c - x)^T M (c - x)."""

    def __init__(self, cen: np.ndarray, mn: np.ndarray, nn: np.ndarray):
        self.cen, self.mn, self.nn9 = cen, mn, nn.reshape(len(nn), 9)
        self.c2 = np.einsum("sk,sk->s", cen, cen)
        self.cm = np.einsum("sk,sk->s", cen, mn)
        self.Mc = np.einsum("skl,sl->sk", nn, cen)
        self.cMc = np.einsum("sk,sk->s", cen, self.Mc)

    def __call__(self, x: np.ndarray):
        r2 = self.c2[None, :] - 2.0 * x @ self.cen.T + np.einsum("ik,ik->i", x, x)[:, None]
        inv = 1.0 / np.maximum(r2, 1e-24)
        mu = (self.cm[None, :] - x @ self.mn.T) * np.sqrt(inv)
        xx = (x[:, :, None] * x[:, None, :]).reshape(len(x), 9)
        m2 = (self.cMc[None, :] - 2.0 * x @ self.Mc.T + xx @ self.nn9.T) * inv
        # a face at a cell's centroid has no direction to it: keep the moments of a unit quantity
        return np.clip(mu, -1.0, 1.0), np.clip(m2 - mu**2, 0.0, 1.0)


def _cell_direction(u: np.ndarray, mn: np.ndarray, nn: np.ndarray):
    """mean and variance of u . n for unit directions u (..., 3) and cells' normal moments."""
    mu = np.einsum("...k,...k->...", u, mn)
    var = np.einsum("...k,...kl,...l->...", u, nn, u) - mu**2
    return mu, var


@dataclass(frozen=True)
class ShapeContextSettings:
    """The `shape_context` group's parameters (see `shape_context`)."""

    n_samples: int = 256
    n_near_samples: int = 1024
    near_area: float = 0.06
    soft_binning: bool = True
    scale_calibration: float = 0.861


@register("shape_context", 270, version="1", columns=SC_COLUMNS, shared=True, settings=ShapeContextSettings)
def shape_context(V: np.ndarray, F: np.ndarray, settings: ShapeContextSettings | None = None, ops=None) -> np.ndarray:
    """Geodesic shape context (270 columns): six 2D histograms, binning b = (distance bins x angle
    bins) in the order 5x4, 5x6, 5x8, 10x4, 10x6, 10x8, each flattened distance-major (column
    `SC b{b}(..) d{x} a{y}`: distance bin x from the face outwards, angle bin y from -90 degrees).
    See the module docstring for the definition, the weights and the per-mesh scale D.

    Parameters: `n_samples` coarse Dijkstra sources (shared with `agd`); `n_near_samples` fine
    sources whose Dijkstra is truncated at the geodesic radius holding a fraction `near_area` of
    the surface (0 turns the near field off); `soft_binning` spreads each cell over the bins
    (False: all of a cell in one bin, noisier); `scale_calibration` maps the sampled estimate of D
    onto the original's (see `geodesic_scale`).

    Meshes of several components: faces of other components are out of reach, as beyond 1.2 D in
    the original; weights stay fractions of the whole mesh's area.
    """
    s = settings or ShapeContextSettings()
    geo = shared_geodesics(V, F, s.n_samples, ops)  # the same Dijkstra run as `agd`'s
    nf = len(F)
    C, N, a = geo.centers, geo.normals, geo.area
    S = len(geo.samples)
    counts = np.bincount(geo.owner, minlength=S).astype(np.float64)
    D = max(geodesic_scale(geo.dist, counts, s.scale_calibration), 1e-12)
    dmax = MAX_DISTANCE * D
    # the near field: the geodesic radius that holds `near_area` of the surface
    rho = area_radius(geo, s.near_area) if s.n_near_samples > 0 and s.near_area > 0 else 0.0
    hist = _Histogrammer(dmax, s.soft_binning)
    cw, cc, cmn, cnn, csig = cell_moments(Cells(geo.owner, S, geo.owner_dist), a, C, N, C[geo.samples])

    # near field: the fine cells within rho of each face, padded to (nf, K)
    if rho > 0:
        fine = farthest_point_sampling(C, min(int(s.n_near_samples), nf))
        fd, _, fsrc = dijkstra(geo.graph, directed=False, indices=fine, min_only=True, return_predecessors=True)
        slot = np.full(nf, -1)
        slot[fine] = np.arange(len(fine))
        reached = fsrc >= 0  # a face no fine sample reaches stays with its coarse cell only
        fown = np.where(reached, slot[np.maximum(fsrc, 0)], 0)
        fa = np.where(reached, a, 0.0)
        fine_cells = Cells(fown, len(fine), np.where(reached, fd, 0.0))
        fw, fc, fmn, fnn, fsig = cell_moments(fine_cells, fa, C, N, C[fine])
        t, i, d = _near_pairs(geo.graph, fine, rho, nf)
        w = np.maximum(fw[t] - np.where(fown[i] == t, fa[i], 0.0), 0.0)  # the face itself is not counted
        # the fine cells near a face stand for that much of the coarse cell their sample lies in
        covered = sp.csr_matrix((fw[t], (i, geo.owner[fine[t]])), shape=(nf, S))
        mask, (nt, nd_, nw) = _padded(i, nf, t, d, w)
    else:  # the face itself is not counted
        covered = sp.csr_matrix((a, (np.arange(nf), geo.owner)), shape=(nf, S))
        mask = np.zeros((nf, 0), bool)

    far_dir = _FarDirections(cc, cmn, cnn)
    H = np.zeros((nf, 270), np.float32)
    # many small matrix products: BLAS threads only add overhead, ruinous on a busy machine
    with threadpool_limits(limits=1, user_api="blas"):
        for lo in range(0, nf, _CHUNK):
            hi = min(lo + _CHUNK, nf)
            Ci = C[lo:hi]
            # far field: the coarse cells, less what the near field covers
            d = geo.dist[:, lo:hi].T.astype(np.float64)
            reach = np.isfinite(d)
            w = np.maximum(cw[None, :] - covered[lo:hi].toarray(), 0.0)
            w[~reach] = 0.0
            d[~reach] = 2 * dmax
            w /= np.maximum(d, rho) / D + WEIGHT_OFFSET
            hist.add(H[lo:hi], d, np.broadcast_to(csig, d.shape), rho, w, far_dir(Ci))
            if mask.shape[1]:  # near field
                tt, dd = nt[lo:hi], nd_[lo:hi]
                ww = np.where(mask[lo:hi], nw[lo:hi], 0.0) / (dd / D + WEIGHT_OFFSET)
                u = fc[tt] - Ci[:, None, :]
                u /= np.maximum(np.linalg.norm(u, axis=2, keepdims=True), 1e-12)
                hist.add(H[lo:hi], dd, fsig[tt], 0.0, ww, _cell_direction(u, fmn[tt], fnn[tt]))
    return H
