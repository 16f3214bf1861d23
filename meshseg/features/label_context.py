"""What a labelling says around each face: the context features of a stacked second stage (model=stacked,
not in the paper: docs/deviations.md G3), computed from per-face class probabilities P (faces, classes) of a
first stage. Kalogerakis et al. 2010 feed such features (label histograms over geodesic distance bins) to a
second boosting stage; here three named groups, each one column per class:

- `smooth_r<r>`: P averaged over the surface around each face at length scale r (the 2010 code's units,
  `geometry.kalogerakis_units`: a shape's radius is about 0.5). The average is the screened-Poisson smoothing
  (A + r^2 L) Q = A P over the face dual graph (A the face areas, L the finite-volume Laplacian with weights
  shared edge length / dual edge length): a kernel that decays as exp(-d / r) with the geodesic distance d
  along the surface, area-weighted, one sparse factorisation per radius. Exact geodesic balls cost 10-15 s a
  radius on a 30k-face mesh (a Dijkstra from every face); this costs 0.3 s. Rows keep summing to 1.
- `share`: the area-weighted share of each class over the whole mesh (the same for all its faces).
- `distance`: the geodesic distance (face dual graph, `geometry.face_dual_graph`) from the face to the
  nearest face whose most probable class is c, in the same units, capped at `distance_cap` (also where no
  face has class c, or none is reachable).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra
from scipy.sparse.linalg import splu

from meshseg.errors import ConfigError
from meshseg.features.geometry import edge_face_pairs, face_areas, face_dual_graph, kalogerakis_units


@dataclass(frozen=True)
class LabelContext:
    """Which context groups, with their parameters (conf/model/stacked.yaml, `context_features`)."""

    radii: tuple[float, ...] = (0.05, 0.15, 0.4)
    share: bool = True
    distance: bool = True
    distance_cap: float = 2.0

    @classmethod
    def of(cls, settings: dict) -> LabelContext:
        unknown = sorted(set(settings) - set(cls.__dataclass_fields__))
        if unknown:
            known = list(cls.__dataclass_fields__)
            raise ConfigError(f"model.context_features: unknown settings {unknown} (known: {known})")
        out = cls(**{**settings, "radii": tuple(float(r) for r in settings.get("radii", cls.radii))})
        if any(not r > 0 for r in out.radii):
            raise ConfigError(f"model.context_features.radii={list(out.radii)}: every radius must be > 0")
        if not out.distance_cap > 0:
            raise ConfigError(f"model.context_features.distance_cap={out.distance_cap}: must be > 0")
        if not (out.radii or out.share or out.distance):
            raise ConfigError("model.context_features: no group left (radii empty, share and distance false)")
        return out

    def names(self, classes: int) -> list[str]:
        """The column names, group by group, one per class."""
        groups = [f"smooth_r{r:g}" for r in self.radii] + ["share"] * self.share + ["distance"] * self.distance
        return [f"{g}/{c}" for g in groups for c in range(classes)]


class MeshContext:
    """The label-independent part of a mesh's context features (its areas, units, dual graph and one
    factorisation per radius), so that several labellings of one mesh cost one setup."""

    def __init__(self, V: np.ndarray, F: np.ndarray, settings: LabelContext):
        self.settings = settings
        self.area = face_areas(V, F)
        self.unit = kalogerakis_units(V, F)[1]
        self.graph = face_dual_graph(V, F)
        self._solvers = [self._smoother(V, F, r * self.unit) for r in settings.radii]

    def _smoother(self, V, F, length: float):
        pairs, shared = edge_face_pairs(F)
        n = len(F)
        # finite-volume weights: the flux across the shared edge over the distance between the face centres
        edge = np.linalg.norm(V[shared[:, 0]] - V[shared[:, 1]], axis=1)
        dual = np.asarray(self.graph[pairs[:, 0], pairs[:, 1]]).ravel()
        W = sp.coo_matrix((edge / dual, (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        W = (W + W.T).tocsr()
        L = sp.diags(np.asarray(W.sum(axis=1)).ravel()) - W
        # a zero-area face would make the system singular where it has no neighbour: a tiny mass keeps it
        mass = np.maximum(self.area, 1e-12 * max(self.area.mean(), 1e-300))
        return mass, splu(sp.csc_matrix(sp.diags(mass) + length**2 * L))

    def features(self, P: np.ndarray) -> np.ndarray:
        """(faces, len(settings.names(classes))) float32 context features of probabilities P (faces, classes)."""
        P = np.asarray(P, dtype=np.float64)
        out = [solver.solve(mass[:, None] * P) for mass, solver in self._solvers]
        if self.settings.share:
            total = self.area.sum()
            share = self.area @ P / total if total > 0 else P.mean(axis=0)
            out.append(np.broadcast_to(share, P.shape))
        if self.settings.distance:
            out.append(self._distances(P.argmax(axis=1), P.shape[1]))
        return np.concatenate(out, axis=1).astype(np.float32)

    def _distances(self, labels: np.ndarray, classes: int) -> np.ndarray:
        cap = self.settings.distance_cap
        d = np.full((len(labels), classes), cap)
        for c in range(classes):
            sources = np.flatnonzero(labels == c)
            if len(sources):
                nearest = dijkstra(self.graph, directed=False, indices=sources, min_only=True)
                d[:, c] = np.minimum(nearest / self.unit, cap)
        return d


def label_context(V: np.ndarray, F: np.ndarray, P: np.ndarray, settings: LabelContext) -> np.ndarray:
    """The context features of probabilities P on mesh (V, F): see the module doc and `MeshContext`."""
    return MeshContext(V, F, settings).features(P)
