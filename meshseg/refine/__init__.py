"""Refinement of per-face probabilities into labels (paper §3.5).

`none`: the argmax. `graphcut_classic`: alpha-expansion with the smoothness -log(theta/pi) * phi
(phi the shared edge's length). `graphcut_agd`: the paper's -log(theta/pi) - omega ||f_u - f_v||
with f the mesh's AGD features. The science is in `graphcut.py`; here the config is read and the
inputs checked.
"""

from __future__ import annotations

import numpy as np

from meshseg.data.mesh import Mesh
from meshseg.errors import ConfigError
from meshseg.refine import graphcut

METHODS = ("none", "graphcut_classic", "graphcut_agd")


def _where(mesh: Mesh) -> str:
    return f"{mesh.source} (mesh {mesh.id!r})" if mesh.id else str(mesh.source)


def check_refine(cfg) -> None:
    """Every setting of a refinement config, checked before any fold trains (each message names the
    setting and what is allowed)."""
    if cfg.name not in METHODS:
        raise ConfigError(f"unknown refinement {cfg.name!r}; known: {list(METHODS)}")
    if cfg.name == "none":
        return
    checks = [
        ("lam", float(cfg.lam) >= 0, ">= 0"),
        ("eps", 0 < float(cfg.eps) < 1, "in (0, 1)"),
        ("convex_factor", float(cfg.convex_factor) >= 0, ">= 0"),
        ("theta_eps", 0 < float(cfg.theta_eps) <= 1, "in (0, 1]"),
        ("n_iter", int(cfg.n_iter) == -1 or int(cfg.n_iter) >= 1, "-1 (until converged) or >= 1"),
    ]
    if cfg.name == "graphcut_classic":
        checks.append(("length_norm", cfg.length_norm in ("mean", "none"), "mean or none"))
    else:
        checks += [
            ("omega", float(cfg.omega) >= 0, ">= 0"),
            ("feature_norm", cfg.feature_norm in ("std", "none"), "std or none"),
        ]
    for key, ok, allowed in checks:
        if not ok:
            raise ConfigError(f"refine.{key}={cfg[key]} is not allowed with refine={cfg.name}: it must be {allowed}")


def refine_labels(mesh: Mesh, probabilities: np.ndarray, cfg, features: np.ndarray | None = None) -> np.ndarray:
    """Labels (faces,) for `mesh` from its (faces, classes) probabilities under refinement `cfg`
    (a `conf/refine/*.yaml` node). `features` are the mesh's (faces, d) AGD features, required by
    `graphcut_agd` and ignored otherwise."""
    P = np.asarray(probabilities)
    if P.ndim != 2 or len(P) != mesh.n_faces:
        raise ValueError(f"{_where(mesh)}: probabilities must be (faces={mesh.n_faces}, classes), got shape {P.shape}")
    if cfg.name not in METHODS:
        raise ConfigError(f"unknown refinement {cfg.name!r}; known: {list(METHODS)}")
    if cfg.name == "graphcut_agd":
        if features is None:
            raise ValueError(f"{_where(mesh)}: refine=graphcut_agd needs the mesh's AGD features, none were given")
        f = np.asarray(features)
        if f.ndim != 2 or len(f) != mesh.n_faces or f.shape[1] == 0:
            raise ValueError(f"{_where(mesh)}: AGD features must be (faces={mesh.n_faces}, d), got shape {f.shape}")
        if not np.isfinite(f).all():
            raise ValueError(f"{_where(mesh)}: AGD features have {(~np.isfinite(f)).sum()} NaN/inf values")
    if cfg.name == "none" or float(cfg.lam) == 0.0:
        return P.argmax(axis=1)

    pairs, angle, length = graphcut.dual_edges(mesh.vertices, mesh.faces)
    theta = graphcut.edge_theta(angle, float(cfg.convex_factor), float(cfg.theta_eps))
    if cfg.name == "graphcut_classic":
        if cfg.length_norm not in ("mean", "none"):
            raise ConfigError(f"unknown length_norm {cfg.length_norm!r}; known: ['mean', 'none']")
        # phi in units of the mesh's mean edge length: lam means the same at any scale
        phi = length / length.mean() if cfg.length_norm == "mean" and length.mean() > 0 else length
        weights = graphcut.classic_weights(theta, phi)
    else:
        f = graphcut.normalize_features(features, cfg.feature_norm)
        weights = graphcut.agd_weights(theta, f, pairs, float(cfg.omega))
    return graphcut.alpha_expansion(P, pairs, weights, float(cfg.lam), float(cfg.eps), int(cfg.n_iter))
