"""Graph-cut refinement (paper §3.5): multi-label alpha-expansion (Boykov et al. 2001) over the face
dual graph, minimising the Potts energy

    E(l) = sum_u -log p_u(l_u) + lam * sum_{edges uv} w_uv [l_u != l_v]

with the smoothness weight w_uv either the classic -log(theta_uv / pi) * phi_uv (phi the shared
edge's length; Shapira et al. 2008, Sidi et al. 2011, Guo et al. 2015) or the paper's
-log(theta_uv / pi) - omega ||f_u - f_v|| (f the per-face AGD features).

theta is the concavity angle of the shared edge. The paper calls it "the dihedral angle" and says
the penalty is large "when the dihedral angle is small (i.e. the faces cause a concavity)", which
would make concave creases -- where part boundaries lie (the minima rule) -- the most expensive
places to cut. Its cited sources use the term the other way round, and so does meshseg: theta is the
exterior dihedral angle (the angle between the two outward face normals: 0 on a flat surface, pi/2
at a right-angled crease), so -log(theta/pi) is large on flat surface and small at sharp creases;
on convex edges theta is scaled by `convex_factor` < 1 (Shapira et al.'s treatment, 0.08 in CGAL's
implementation of it), which makes convex ridges about as dear to cut as flat surface.

Plain numpy arrays in and out; everything is vectorised except the max-flow itself (gco-wrapper,
the GCO v3 C++ library).
"""

from __future__ import annotations

import numpy as np

from meshseg.errors import ConfigError
from meshseg.features.geometry import edge_face_pairs, face_centers, per_face_normals

# gco works in int32 energy terms (GCO_MAX_ENERGYTERM = 1e7 is its overflow guard): meshseg scales
# the largest unary or pairwise term to this many units itself, a resolution of 1e-6 of that term
_MAX_TERM = 1_000_000


def dihedral_edges(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The face dual graph with its geometry: (pairs (E, 2) with pairs[:, 0] < pairs[:, 1],
    angle (E,), length (E,)).

    angle is the signed exterior dihedral angle of the shared edge in [-pi, pi]: the angle between
    the two face normals, positive where the edge is convex (a ridge), negative where it is concave
    (a valley), 0 on a flat surface and on a degenerate (zero-area) face. Faces must be consistently
    oriented with outward normals for the sign; where the shared edge runs the same way in both
    faces (a locally flipped face) the second normal is flipped first, so the magnitude stays right.
    length is the shared edge's length. A non-manifold edge gives every pair of its faces.
    """
    F = np.asarray(F, np.int64)
    pairs, shared = edge_face_pairs(F)
    pairs = np.sort(pairs, axis=1)  # gco wants the smaller site first
    u, v = pairs[:, 0], pairs[:, 1]
    n = per_face_normals(V, F)
    nu, nv = n[u], n[v]
    # the shared edge runs a -> b in face u's winding and b -> a in v's on an oriented mesh
    flipped = _runs_forward(F[u], shared) == _runs_forward(F[v], shared)
    nv = np.where(flipped[:, None], -nv, nv)
    angle = np.arctan2(np.linalg.norm(np.cross(nu, nv), axis=1), np.einsum("ij,ij->i", nu, nv))
    # convex where the normals diverge along the path from u's centre to v's
    c = face_centers(V, F)
    convex = np.einsum("ij,ij->i", c[v] - c[u], nv - nu) > 0
    angle = np.where(convex, angle, -angle)
    length = np.linalg.norm(V[shared[:, 0]] - V[shared[:, 1]], axis=1)
    return pairs, angle, length


def _runs_forward(faces: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """Whether edge[:, 0] -> edge[:, 1] is one of the directed edges of each face's winding."""
    nxt = np.roll(faces, -1, axis=1)
    return np.any((faces == edge[:, :1]) & (nxt == edge[:, 1:]), axis=1)


def edge_theta(angle: np.ndarray, convex_factor: float = 0.08, theta_eps: float = 1e-3) -> np.ndarray:
    """The theta of -log(theta/pi) from signed exterior dihedral angles (`dihedral_edges`).

    Concave edges: theta = |angle| (pi at a knife-sharp valley: free to cut; 0 on flat surface).
    Convex edges: theta = convex_factor * |angle| (1: treat a ridge like a valley of the same angle;
    small: ridges cost about as much as flat surface). Clipped to [theta_eps * pi, pi] so flat and
    degenerate faces give a finite cost -log(theta_eps).
    """
    if not 0 < theta_eps <= 1:
        raise ConfigError(f"theta_eps must be in (0, 1], got {theta_eps}")
    if not convex_factor >= 0:
        raise ConfigError(f"convex_factor must be >= 0, got {convex_factor}")
    a = np.abs(np.asarray(angle, np.float64))
    theta = np.where(np.asarray(angle) > 0, convex_factor * a, a)
    return np.clip(theta, theta_eps * np.pi, np.pi)


def concavity_cost(theta: np.ndarray) -> np.ndarray:
    """-log(theta / pi), >= 0 for theta in (0, pi]."""
    return np.maximum(-np.log(np.asarray(theta, np.float64) / np.pi), 0.0)


def classic_weights(theta: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Classic smoothness weights -log(theta/pi) * phi, phi the shared edge's length (E,)."""
    return concavity_cost(theta) * np.asarray(length, np.float64)


def agd_weights(theta: np.ndarray, f: np.ndarray, pairs: np.ndarray, omega: float) -> np.ndarray:
    """The paper's smoothness weights -log(theta/pi) - omega ||f_u - f_v||, clamped to >= 0 (E,).

    The clamp: a graph cut needs non-negative pairwise costs, and a negative one would *reward*
    a label change; where the feature jump outweighs the concavity term the cut is simply free.
    """
    f = np.asarray(f, np.float64)
    jump = np.linalg.norm(f[pairs[:, 0]] - f[pairs[:, 1]], axis=1)
    return np.maximum(concavity_cost(theta) - omega * jump, 0.0)


def normalize_features(f: np.ndarray, mode: str = "std") -> np.ndarray:
    """Per-mesh scaling of the features of the AGD term: `std` divides each column by its standard
    deviation over the mesh's faces (constant columns become 0, so they add nothing); `none` keeps
    them as given. Makes omega independent of the mesh's units and of the columns' ranges."""
    f = np.asarray(f, np.float64)
    if mode == "none":
        return f
    if mode != "std":
        raise ConfigError(f"unknown feature normalisation {mode!r}; known: ['std', 'none']")
    sd = f.std(axis=0)
    # relative guard: a float32 column constant up to rounding is constant
    keep = sd > 1e-6 * np.maximum(np.abs(f).max(axis=0), 1e-300)
    return np.where(keep, (f - f.mean(axis=0)) / np.where(keep, sd, 1.0), 0.0)


def unary_costs(probabilities: np.ndarray, eps: float) -> np.ndarray:
    """Data term -log p_u(l), probabilities clipped to [eps, 1] first (F, L)."""
    if not 0 < eps <= 1:
        raise ValueError(f"eps must be in (0, 1], got {eps}")
    return -np.log(np.clip(np.asarray(probabilities, np.float64), eps, 1.0))


def potts_energy(
    labels: np.ndarray, probabilities: np.ndarray, pairs: np.ndarray, weights: np.ndarray, lam: float, eps: float
) -> float:
    """E(labels) = sum_u -log p_u(l_u) + lam * sum_uv w_uv [l_u != l_v], in floating point."""
    labels = np.asarray(labels)
    data = unary_costs(probabilities, eps)[np.arange(len(labels)), labels].sum()
    cut = labels[pairs[:, 0]] != labels[pairs[:, 1]]
    return float(data + lam * np.asarray(weights, np.float64)[cut].sum())


def alpha_expansion(
    probabilities: np.ndarray, pairs: np.ndarray, weights: np.ndarray, lam: float, eps: float = 1e-6, n_iter: int = -1
) -> np.ndarray:
    """Labels (F,) minimising the Potts energy (see `potts_energy`) by alpha-expansion.

    Starts from the argmax labels and runs expansion cycles until none lowers the energy
    (`n_iter` = -1) or for `n_iter` cycles. Alpha-expansion is exact for two labels and within a
    factor 2 of the optimum for more (Boykov et al. 2001). Energies are scaled to integers here so
    that the largest term is `_MAX_TERM` units: gco's own float conversion truncates edge weights
    to 1e-3 of the largest term.
    """
    import gco

    P = np.asarray(probabilities, np.float64)
    if P.ndim != 2 or len(P) == 0:
        raise ValueError(f"probabilities must be a non-empty (faces, labels) array, got shape {P.shape}")
    if lam < 0:
        raise ValueError(f"lam must be >= 0, got {lam}")
    start = P.argmax(axis=1)
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    w = lam * np.asarray(weights, np.float64)
    if len(w) != len(pairs):
        raise ValueError(f"{len(w)} weights for {len(pairs)} edges")
    if not (np.isfinite(w).all() and (w >= 0).all()):
        raise ValueError("smoothness weights must be finite and >= 0")
    live = w > 0
    pairs, w = np.sort(pairs[live], axis=1), w[live]
    if P.shape[1] == 1 or len(w) == 0:
        return start
    U = unary_costs(P, eps)
    U -= U.min(axis=1, keepdims=True)  # a per-face constant changes no minimiser, saves range
    top = max(U.max(), w.max())
    scale = _MAX_TERM / top
    unary = np.rint(U * scale).astype(np.int32)
    edge_w = np.rint(w * scale).astype(np.int32)
    potts = (1 - np.eye(P.shape[1])).astype(np.int32)
    # all-integer input with down_weight_factor 1: gco then passes the terms through unchanged
    labels = gco.cut_general_graph(
        pairs.astype(np.int32),
        edge_w,
        unary,
        potts,
        n_iter=n_iter,
        algorithm="expansion",
        init_labels=start,
        down_weight_factor=1,
    )
    return np.asarray(labels, np.int64)
