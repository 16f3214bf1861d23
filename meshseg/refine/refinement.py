"""Refinements of per-face probabilities into labels (paper §3.5), each a class named by `_target_` in
`conf/refine/*.yaml`; the science is in `graphcut.py` (plain arrays).

A refinement checks its settings when built (before any fold trains), declares in `needs` the feature
groups it reads per mesh (the run computes them, or reads them from the feature cache, with the run's
own group parameters), and is called as `refinement(mesh, probabilities, features)`.

`none` (`Argmax`): the argmax. `graphcut_classic`: alpha-expansion with the smoothness
-log(theta/pi) * phi (phi the shared edge's length). `graphcut_agd`: the paper's
-log(theta/pi) - omega ||f_u - f_v|| with f the mesh's AGD features.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from omegaconf import OmegaConf

from meshseg.data.mesh import Mesh
from meshseg.errors import ConfigError
from meshseg.refine import graphcut, search


def _where(mesh: Mesh) -> str:
    return f"{mesh.source} (mesh {mesh.id!r})" if mesh.id else str(mesh.source)


def _check(name: str, checks) -> None:
    for key, value, ok, allowed in checks:
        if not ok:
            raise ConfigError(f"refine.{key}={value} is not allowed with refine={name}: it must be {allowed}")


class Refinement:
    """Labels (faces,) from a mesh's (faces, classes) probabilities."""

    name = "refinement"
    needs: tuple[str, ...] = ()  # feature groups read per mesh, in this order, as one (faces, d) array
    search: dict | None = None  # a grid of its settings to choose from per fold (meshseg/refine/search.py)

    def __call__(self, mesh: Mesh, probabilities: np.ndarray, features: np.ndarray | None = None) -> np.ndarray:
        P = np.asarray(probabilities)
        if P.ndim != 2 or len(P) != mesh.n_faces:
            raise ValueError(
                f"{_where(mesh)}: probabilities must be (faces={mesh.n_faces}, classes), got shape {P.shape}"
            )
        if self.needs:
            f = None if features is None else np.asarray(features)
            where, what = _where(mesh), "+".join(self.needs).upper()
            if f is None:
                raise ValueError(f"{where}: refine={self.name} needs the mesh's {what} features, none were given")
            if f.ndim != 2 or len(f) != mesh.n_faces or f.shape[1] == 0:
                raise ValueError(f"{where}: {what} features must be (faces={mesh.n_faces}, d), got shape {f.shape}")
            if not np.isfinite(f).all():
                raise ValueError(f"{where}: {what} features have {(~np.isfinite(f)).sum()} NaN/inf values")
        return self.labels(mesh, P, features)

    def labels(self, mesh: Mesh, P: np.ndarray, features: np.ndarray | None) -> np.ndarray:
        raise NotImplementedError

    def fitted(self, preds, source, score, timings):
        """The refinement a fold applies, fitted like its model: as configured, or with `search` its settings
        chosen on the training meshes the fitter held out (meshseg.refine.search.fit_refinement)."""
        return search.fit_refinement(self, preds, source, score, timings)


class Argmax(Refinement):
    """No refinement: each face's most probable label."""

    name = "none"

    def labels(self, mesh, P, features):
        return P.argmax(axis=1)


# The graph cuts are dataclasses: their fields are their settings (the keys of conf/refine/*.yaml), so a
# setting a class does not take is refused by name when it is built.
@dataclass
class GraphCut(Refinement):
    """Alpha-expansion (Boykov et al. 2001) over the face dual graph; subclasses give the smoothness
    weight of each dual edge."""

    lam: float = 2.0
    eps: float = 1e-6
    convex_factor: float = 0.08
    theta_eps: float = 1e-3
    n_iter: int = -1
    search: dict | None = None

    def __post_init__(self):
        _check(
            self.name,
            [
                ("lam", self.lam, float(self.lam) >= 0, ">= 0"),
                ("eps", self.eps, 0 < float(self.eps) < 1, "in (0, 1)"),
                ("convex_factor", self.convex_factor, float(self.convex_factor) >= 0, ">= 0"),
                ("theta_eps", self.theta_eps, 0 < float(self.theta_eps) <= 1, "in (0, 1]"),
                (
                    "n_iter",
                    self.n_iter,
                    int(self.n_iter) == -1 or int(self.n_iter) >= 1,
                    "-1 (until converged) or >= 1",
                ),
            ],
        )
        self.lam, self.eps, self.n_iter = float(self.lam), float(self.eps), int(self.n_iter)
        self.convex_factor, self.theta_eps = float(self.convex_factor), float(self.theta_eps)

    def weights(self, mesh, pairs, theta, length, features) -> np.ndarray:
        raise NotImplementedError

    def labels(self, mesh, P, features):
        if self.lam == 0.0:
            return P.argmax(axis=1)
        pairs, angle, length = graphcut.dihedral_edges(mesh.vertices, mesh.faces)
        theta = graphcut.edge_theta(angle, self.convex_factor, self.theta_eps)
        weights = self.weights(mesh, pairs, theta, length, features)
        return graphcut.alpha_expansion(P, pairs, weights, self.lam, self.eps, self.n_iter)


@dataclass
class GraphCutClassic(GraphCut):
    """Smoothness -log(theta/pi) * phi, phi the shared edge's length (Shapira et al. 2008)."""

    name = "graphcut_classic"
    length_norm: str = "mean"

    def __post_init__(self):
        super().__post_init__()
        _check(self.name, [("length_norm", self.length_norm, self.length_norm in ("mean", "none"), "mean or none")])

    def weights(self, mesh, pairs, theta, length, features):
        # phi in units of the mesh's mean edge length: lam means the same at any scale
        phi = length / length.mean() if self.length_norm == "mean" and length.mean() > 0 else length
        return graphcut.classic_weights(theta, phi)


@dataclass
class GraphCutAGD(GraphCut):
    """The paper's smoothness -log(theta/pi) - omega ||f_u - f_v||, f the mesh's AGD features."""

    name = "graphcut_agd"
    needs = ("agd",)
    omega: float = 2.0
    feature_norm: str = "std"

    def __post_init__(self):
        super().__post_init__()
        _check(
            self.name,
            [
                ("omega", self.omega, float(self.omega) >= 0, ">= 0"),
                ("feature_norm", self.feature_norm, self.feature_norm in ("std", "none"), "std or none"),
            ],
        )
        self.omega = float(self.omega)

    def weights(self, mesh, pairs, theta, length, features):
        f = graphcut.normalize_features(features, self.feature_norm)
        return graphcut.agd_weights(theta, f, pairs, self.omega)


def build_refinement(cfg) -> Refinement:
    """The refinement a `conf/refine/*.yaml` node names, its settings checked."""
    from meshseg.instantiate import build

    refinement = build(cfg, f"refine={cfg.get('name', '?')}")
    if not isinstance(refinement, Refinement):
        raise ConfigError(f"refine={cfg.get('name', '?')}: {cfg._target_} is not a meshseg.refine.Refinement")
    if refinement.search is not None:  # every grid point checked now, before any fold trains
        grid = refinement.search
        refinement.search = OmegaConf.to_container(grid) if OmegaConf.is_config(grid) else grid
        search.candidates(refinement, refinement.search)
    return refinement


def refine_labels(mesh: Mesh, probabilities: np.ndarray, cfg, features: np.ndarray | None = None) -> np.ndarray:
    """Labels (faces,) for `mesh` under the refinement config `cfg` (one call: tests, benchmarks)."""
    return build_refinement(cfg)(mesh, probabilities, features)
