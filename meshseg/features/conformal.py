"""Conformal factor (Ben-Chen & Gotsman 2008) and the paper's smoothed conformal factors (§3.1).

The conformal factor Φ solves L Φ = K^T − K^orig: K^orig is the angle defect at each vertex,
K^T spreads the same total curvature over the vertices in proportion to their areas, and L is
the cotangent Laplacian. Φ is the log of the metric scale that would make the curvature uniform,
so it is LOW where curvature is concentrated: sharp convex tips and thin protrusions (which the
conformal map shrinks), high on flat and saddle regions. Φ is dimensionless: it does not change
when the mesh is scaled.

Conventions and choices (they change values; see the group docstrings):
- L is positive semi-definite, L = −igl.cotmatrix (Ben-Chen's sign: off-diagonals −(cot α + cot β)/2).
  With igl's negative semi-definite sign Φ would flip.
- L is singular (constants per connected component), so the right-hand side and the gauge are
  fixed per component: K^T spreads each component's own total curvature over that component's
  area (the paper spreads the mesh total over the mesh area; the two agree on a connected mesh,
  and only the per-component form is solvable on a disconnected one), and Φ has zero
  area-weighted mean on every component.
- The total curvature of a component is taken combinatorially, 2π·#vertices − π·#faces (equal to
  Σ angle defects, since a triangle's angles sum to π), so that it is exactly 0 on a genus-1
  component instead of rounding noise.
- Faces of (near) zero area carry no cotangent weights (their cotangents are unbounded); they
  still count in the angle defects and vertex areas.
"""

from __future__ import annotations

from dataclasses import dataclass

import igl
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import splu

from meshseg.errors import ConfigError
from meshseg.features.geometry import face_areas, vertex_to_face
from meshseg.features.registry import register

# a face whose area is below this fraction of its longest edge squared is treated as degenerate
_DEGENERATE = 1e-10


def angle_defect(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Per-vertex angle defect 2π − Σ incident corner angles (igl.gaussian_curvature's K^orig),
    with corner angles from atan2 so that degenerate faces give finite angles summing to π."""
    e1 = V[F[:, [1, 2, 0]]] - V[F]  # edge leaving each corner
    e2 = V[F[:, [2, 0, 1]]] - V[F]  # edge arriving at each corner, reversed
    ang = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=2), np.einsum("fcd,fcd->fc", e1, e2))
    # a face with a zero-length edge has no defined angles: give it an equilateral split
    zero_edge = (np.linalg.norm(e1, axis=2) == 0).any(axis=1)
    ang[zero_edge] = np.pi / 3
    return 2 * np.pi - np.bincount(F.ravel(), ang.ravel(), minlength=len(V))


def vertex_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Barycentric vertex area: a third of the area of every incident face."""
    return np.bincount(F.ravel(), np.repeat(face_areas(V, F) / 3, 3), minlength=len(V))


def cotan_laplacian(V: np.ndarray, F: np.ndarray) -> sp.csc_matrix:
    """Positive semi-definite cotangent Laplacian (−igl.cotmatrix) over the non-degenerate faces."""
    edges = V[F[:, [1, 2, 0]]] - V[F]
    longest = (edges**2).sum(axis=2).max(axis=1)
    ok = face_areas(V, F) > _DEGENERATE * longest
    if not ok.any():
        return sp.csc_matrix((len(V), len(V)))
    return (-igl.cotmatrix(V, F[ok])).tocsc()


def vertex_components(F: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """Connected components of the vertices through the faces' edges: (count, label per vertex)."""
    e = F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    g = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)


def target_curvature(V: np.ndarray, F: np.ndarray, labels: np.ndarray, n_comp: int, total: str = "mesh") -> np.ndarray:
    """K^T: each component's total curvature spread over its vertices in proportion to their area.

    total="mesh": the component's own total (2π·#vertices − π·#faces = 2πχ when closed);
    total="sphere": 4π on every component, whatever its genus."""
    n = len(V)
    if total == "sphere":
        total = np.full(n_comp, 4 * np.pi)
    else:
        total = 2 * np.pi * np.bincount(labels, minlength=n_comp) - np.pi * np.bincount(
            labels[F[:, 0]], minlength=n_comp
        )
    a = vertex_areas(V, F)
    area = np.bincount(labels, a, minlength=n_comp)
    share = np.divide(a, area[labels], out=np.full(n, 0.0), where=area[labels] > 0)
    # a component of zero area: spread its curvature evenly over its vertices
    count = np.bincount(labels, minlength=n_comp)
    share = np.where(area[labels] > 0, share, 1.0 / count[labels])
    return total[labels] * share


def solve_gauged(L: sp.spmatrix, b: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Solve the PSD Laplacian system L x = b with zero `weights`-weighted mean per component.

    One vertex per component of L's graph is pinned by adding a diagonal penalty there: for a
    right-hand side with zero sum on the component this leaves L x = b exact (summing the rows
    gives x_pinned = 0), and the matrix becomes non-singular. Components are those of L's
    non-zero weights, so vertices left without weights (only degenerate faces) are pinned alone.
    """
    n = L.shape[0]
    g = L.copy()
    g.setdiag(0)
    g.eliminate_zeros()
    n_comp, labels = connected_components(g, directed=False)
    first = np.full(n_comp, n)
    np.minimum.at(first, labels, np.arange(n))
    scale = np.abs(L.diagonal()).mean() or 1.0
    pin = np.zeros(n)
    pin[first] = scale
    A = (L + sp.diags(pin)).tocsc()
    x = splu(A, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True}).solve(b)
    w = np.bincount(labels, weights, minlength=n_comp)
    sw = np.bincount(labels, weights * x, minlength=n_comp)
    # unweighted mean where a component has no area
    cnt = np.bincount(labels, minlength=n_comp)
    mean = np.where(w > 0, sw / np.where(w > 0, w, 1), np.bincount(labels, x, minlength=n_comp) / cnt)
    return x - mean[labels]


def conformal_factor(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Per-vertex conformal factor Φ: L Φ = K^T − K^orig on the mesh (V, F), zero mean per component."""
    n_comp, labels = vertex_components(F, len(V))
    b = target_curvature(V, F, labels, n_comp) - angle_defect(V, F)
    return solve_gauged(cotan_laplacian(V, F), b, vertex_areas(V, F))


def neighbour_average(V: np.ndarray, F: np.ndarray, weights: str = "cotan") -> sp.csr_matrix:
    """n x n matrix averaging each vertex's edge neighbours, the operator of Taubin smoothing.

    weights="cotan": cotangent weights of (V, F), negative ones set to 0 so that the average is a
    convex combination (Taubin's condition); the step then moves vertices (nearly) along the
    mean-curvature normal, so the areas change with the geometry rather than the tessellation. weights="uniform": every
    neighbour once (Taubin's umbrella); it also slides vertices tangentially towards regular
    triangles. A vertex without positive weights maps to 0 (and is not moved)."""
    n = len(V)
    if weights == "cotan":
        W = (-cotan_laplacian(V, F)).tocsr()
        W.setdiag(0)
        W.data = np.maximum(W.data, 0)
    elif weights == "uniform":
        e = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        e = np.unique(e[:, 0] * np.int64(n) + e[:, 1])
        i, j = e // n, e % n
        W = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    else:
        raise ConfigError(f"cf_smooth: taubin_weights must be 'cotan' or 'uniform', not {weights!r}")
    W.eliminate_zeros()
    deg = np.asarray(W.sum(axis=1)).ravel()
    return (sp.diags(np.divide(1.0, deg, out=np.zeros(n), where=deg > 0)) @ W).tocsr()


def taubin_smooth(V: np.ndarray, mean_nb: sp.spmatrix, lam: float, mu: float, pairs: int) -> np.ndarray:
    """`pairs` λ|μ steps of Taubin's non-shrinking smoothing with the averaging operator `mean_nb`
    (see neighbour_average): V ← V + λ (mean of neighbours − V), then V ← V + μ (mean of
    neighbours − V). Vertices without neighbours stay put."""
    moves = (np.asarray(mean_nb.sum(axis=1)).ravel() > 0)[:, None]
    V = V.copy()
    for _ in range(pairs):
        for step in (lam, mu):
            V += step * moves * (mean_nb @ V - V)
    return V


@dataclass(frozen=True)
class TaubinSettings:
    """The `cf_smooth` group's parameters: how the mesh is smoothed and what its CF is solved on (see
    `cf_smooth`)."""

    taubin_lambda: float = 0.5
    taubin_mu: float = -0.53
    taubin_pairs: int = 1
    taubin_weights: str = "cotan"
    laplacian_mesh: str = "smoothed"
    target_total: str = "mesh"


def smoothed_conformal_factors(
    V: np.ndarray, F: np.ndarray, settings: TaubinSettings | None = None, iterations: int = 5
) -> np.ndarray:
    """Per-vertex Φ^s_i, i = 1..iterations, as an (iterations, n) array: L Φ^s_i = K^{sT}_i − K^T, with
    M^s_i = M^s_{i−1} after `taubin_pairs` λ|μ steps (neighbour weights `taubin_weights` of the
    original mesh), L the Laplacian of M^s_i (`laplacian_mesh="smoothed"`) or of the original mesh
    ("original"), and both targets spreading `target_total` (see target_curvature)."""
    s = settings or TaubinSettings()
    laplacian_mesh, target_total = s.laplacian_mesh, s.target_total
    if laplacian_mesh not in ("smoothed", "original"):
        raise ConfigError(f"cf_smooth: laplacian_mesh must be 'smoothed' or 'original', not {laplacian_mesh!r}")
    if target_total not in ("mesh", "sphere"):
        raise ConfigError(f"cf_smooth: target_total must be 'mesh' or 'sphere', not {target_total!r}")
    n_comp, labels = vertex_components(F, len(V))
    k_target = target_curvature(V, F, labels, n_comp, target_total)
    L0 = cotan_laplacian(V, F) if laplacian_mesh == "original" else None
    mean_nb = neighbour_average(V, F, s.taubin_weights)
    out, Vs = [], V
    for _ in range(iterations):
        Vs = taubin_smooth(Vs, mean_nb, s.taubin_lambda, s.taubin_mu, s.taubin_pairs)
        b = target_curvature(Vs, F, labels, n_comp, target_total) - k_target
        L = L0 if L0 is not None else cotan_laplacian(Vs, F)
        out.append(solve_gauged(L, b, vertex_areas(Vs, F)))
    return np.array(out)


def _compact(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no face uses (they would be isolated unknowns); faces re-indexed."""
    used, Fc = np.unique(F, return_inverse=True)
    return np.asarray(V, np.float64)[used], Fc.reshape(F.shape)


@register("cf0", 1, columns=["cf0"])
def cf0(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """CF0: the conformal factor Φ of the mesh (Ben-Chen & Gotsman 2008), one column.

    Per vertex L Φ = K^T − K^orig (module docstring: PSD cotangent L, per-component K^T and zero
    area-weighted mean per component); per face the mean of its three vertices. No other
    normalisation: Φ is dimensionless and invariant to scale and rigid motion. Low on sharp tips
    and thin protrusions, high on flat and saddle-shaped regions.
    """
    V, F = _compact(V, F)
    return vertex_to_face(conformal_factor(V, F), F)[:, None]


@register("cf_smooth", 5, columns=[f"cf{i}" for i in range(1, 6)], settings=TaubinSettings)
def cf_smooth(V: np.ndarray, F: np.ndarray, settings: TaubinSettings | None = None) -> np.ndarray:
    """CF1..CF5: the paper's smoothed conformal factors (§3.1), one column per smoothing iteration.

    M^s_i is the mesh after i Taubin iterations (λ = `taubin_lambda`, μ = `taubin_mu`; one
    iteration = `taubin_pairs` λ|μ step pairs, as in Taubin 1995 where an iteration is one shrink
    and one inflate step). The neighbour weights (`taubin_weights`) are the original mesh's
    clamped cotangent weights by default, which move vertices along the normal only; Taubin's
    uniform weights also slide them along the surface, which redistributes area by tessellation
    alone, against the paper's aim for these features. Column i solves L_i Φ^s_i = K^{sT}_i − K^T:
    K^{sT}_i and K^T are the target curvatures of M^s_i and of the original mesh; L_i is the
    Laplacian of M^s_i (the paper computes "CF on these meshes"; `laplacian_mesh="original"` uses
    the original mesh's L instead). As the total curvature is the same on both meshes, the right
    side is total × (relative vertex area after smoothing − before): Φ^s_i measures how smoothing
    redistributes area, lowest where smoothing shrinks the surface most (thin protrusions, sharp
    tips). With the paper's total (`target_total="mesh"`, 2πχ) it is identically zero on a genus-1
    component and flips sign with the Euler characteristic; `target_total="sphere"` uses 4π on
    every component instead (same values on genus 0, genus-independent elsewhere). Gauge,
    per-face mapping and (lack of) normalisation as for cf0.
    """
    V, F = _compact(V, F)
    phi = smoothed_conformal_factors(V, F, settings, 5)
    return vertex_to_face(phi.T, F)
