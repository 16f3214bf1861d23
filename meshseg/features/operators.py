"""One mesh's shared operators: the expensive intermediate results that several feature groups
derive their columns from, computed at most once per mesh and parameter value.

`MeshOperators(V, F, key)` stands for "this mesh": `FeatureSet.compute` builds one per call and
hands it to every group registered with `shared=True` (keyword `ops`), so `hks` and `sihks` share
one Laplace–Beltrami eigen-solve and `agd` and `shape_context` one Dijkstra run. The memo lives on
the object, not in the module: it is dropped with the object, and another mesh gets another
object, so results can never leak from one mesh to another. The science stays in the family
modules (`heat_kernel.laplace_beltrami_eigenpairs`, `agd.sampled_geodesics`, pure functions);
this module only memoises them.

Imports point one way: this module imports the families, never the reverse (a group receives
the object as an argument), and the feature cache adds this module to the code version of every
shared group (`cache.code_version`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from meshseg.features.agd import SampledGeodesics, sampled_geodesics
from meshseg.features.heat_kernel import laplace_beltrami_eigenpairs


class MeshOperators:
    """Lazily computed, memoised per-mesh operators of the mesh (V, F).

    `key` names the mesh (its `Mesh.content_hash`) in messages; the memo does not depend on it,
    since it belongs to this object and this object to one mesh.
    """

    def __init__(self, V: np.ndarray, F: np.ndarray, key: str | None = None):
        self.V = V
        self.F = F
        self.key = key
        self._memo: dict[tuple, object] = {}

    def __repr__(self) -> str:
        name = self.key if self.key is not None else f"{len(self.V)} vertices"
        return f"MeshOperators({name}, {len(self.F)} faces, {len(self._memo)} computed)"

    def describes(self, V: np.ndarray, F: np.ndarray) -> bool:
        """Whether (V, F) is this object's mesh: the same arrays, or arrays of the same content."""
        if V is self.V and F is self.F:
            return True
        return np.array_equal(V, self.V) and np.array_equal(F, self.F)  # False on another shape

    def eigenpairs(self, n_eigen: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """`heat_kernel.laplace_beltrami_eigenpairs(V, F, n_eigen)`, computed once per `n_eigen`."""
        return self._get("eigenpairs", laplace_beltrami_eigenpairs, int(n_eigen))

    def geodesics(self, n_samples: int) -> SampledGeodesics:
        """`agd.sampled_geodesics(V, F, n_samples)`, computed once per `n_samples`."""
        return self._get("geodesics", sampled_geodesics, int(n_samples))

    def _get(self, name: str, compute: Callable, *params):
        key = (name, *params)
        if key not in self._memo:
            self._memo[key] = compute(self.V, self.F, *params)
        return self._memo[key]
