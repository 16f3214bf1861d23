"""Feature groups by name: each a function (V, F, **params) -> (F, dim) float32.

A family module registers its groups with `@register`; the registry knows each group's width,
column names, default parameters and a version string that is part of every cache key — bump it
when a group's values change. The parameters are the function's keyword defaults, or, for a group
with many, the fields of a frozen settings dataclass (`register(settings=...)`) that the function
takes as its third argument: `fn(V, F, settings)`.

A group registered with `shared=True` also takes the keyword `ops`: the mesh's
`operators.MeshOperators`, whose memoised eigenpairs and geodesics it shares with the other groups
computed for the same mesh (`FeatureSet.compute` passes one per mesh). Its function must accept
`ops=None` and then compute what it needs itself, so a direct call needs no operators. This module
never imports `operators`: every group's cache code version follows this module's imports.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from meshseg.errors import ConfigError


@dataclass(frozen=True)
class Group:
    name: str
    fn: Callable[..., np.ndarray]
    dim: int
    version: str
    columns: tuple[str, ...]
    defaults: dict = field(default_factory=dict)
    shared: bool = False  # takes the mesh's shared operators as keyword `ops`
    settings: type | None = None  # the parameters' dataclass, handed to fn as one argument

    def params(self, overrides: dict | None = None) -> dict:
        """Default parameters updated by `overrides`; an unknown name is an error."""
        overrides = dict(overrides or {})
        unknown = sorted(set(overrides) - set(self.defaults))
        if unknown:
            raise ConfigError(
                f"feature group {self.name!r} has no parameters {unknown}; it has {sorted(self.defaults)}"
            )
        for key, value in overrides.items():
            default = self.defaults[key]
            counts = isinstance(default, int) and not isinstance(default, bool) and default >= 1
            if counts and not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                # a count (samples, eigenpairs, rays, neighbours): 0 or a fraction would fail deep inside
                raise ConfigError(
                    f"features.params.{self.name}.{key}={value} is not allowed: it must be an integer >= 1"
                )
        return {**self.defaults, **overrides}

    def __call__(self, V: np.ndarray, F: np.ndarray, ops=None, **params) -> np.ndarray:
        """The (F, dim) float32 matrix of (V, F). `ops`: the mesh's `MeshOperators`, handed to a shared
        group (None: it computes what it needs itself); ignored by the others."""
        params = self.params(params)
        if self.shared:
            if ops is not None and not ops.describes(V, F):
                raise ValueError(f"feature group {self.name!r}: the shared operators given are those of another mesh")
            params["ops"] = ops
        if self.settings is not None:
            ops = {"ops": params.pop("ops")} if self.shared else {}
            X = self.fn(V, F, self.settings(**params), **ops)
        else:
            X = self.fn(V, F, **params)
        X = np.asarray(X, dtype=np.float32)
        if X.shape != (len(F), self.dim):
            raise RuntimeError(f"feature group {self.name!r} returned shape {X.shape}, expected {(len(F), self.dim)}")
        return X


GROUPS: dict[str, Group] = {}


def register(
    name: str, dim: int, version: str = "1", columns: list[str] | None = None, shared: bool = False, settings=None
):
    """Decorator: add `fn(V, F, **params)` to GROUPS as `name` with `dim` columns; `shared`: fn also
    takes the mesh's shared operators as keyword `ops` (not a parameter: no part of the cache key);
    `settings`: a frozen dataclass whose fields are the parameters, fn being `fn(V, F, settings)`."""

    def wrap(fn):
        if name in GROUPS:
            raise ValueError(f"feature group {name!r} registered twice")
        sig = inspect.signature(fn)
        if shared and (sig.parameters.get("ops") is None or sig.parameters["ops"].default is not None):
            raise ValueError(f"feature group {name!r} is shared: its function needs the keyword ops=None")
        if settings is not None:
            defaults = {f.name: f.default for f in dataclasses.fields(settings)}
        else:
            defaults = {
                k: p.default
                for k, p in list(sig.parameters.items())[2:]
                if p.default is not inspect.Parameter.empty and not (shared and k == "ops")
            }
        cols = tuple(columns) if columns is not None else tuple(f"{name}[{i}]" for i in range(dim))
        if len(cols) != dim:
            raise ValueError(f"feature group {name!r}: {len(cols)} column names for {dim} columns")
        GROUPS[name] = Group(name, fn, dim, version, cols, defaults, shared, settings)
        return fn

    return wrap


def get_group(name: str) -> Group:
    from meshseg import features  # noqa: F401  (importing the package registers every family)

    if name not in GROUPS:
        raise ConfigError(f"unknown feature group {name!r}; known: {sorted(GROUPS)}")
    return GROUPS[name]
