"""On-disk cache of feature groups, keyed by (mesh content, group, parameters, code version).

One `.npz` per key, written atomically (temporary file + rename). Zip's CRC and a shape check catch
a corrupt or truncated file, which is then recomputed and replaced, never trusted.
"""

from __future__ import annotations

import ast
import hashlib
import importlib
import importlib.util
import inspect
import json
import logging
import os
from functools import cache
from pathlib import Path

import numpy as np

from meshseg.data.io import atomic_write
from meshseg.errors import ConfigError
from meshseg.features.registry import Group

log = logging.getLogger(__name__)


_OPERATORS = "meshseg.features.operators"  # a shared group runs it without importing it (it gets `ops`)


def code_version(group: Group) -> str:
    """The group's declared version plus a hash of the source of every meshseg module its code runs:
    its own module and, transitively, each meshseg module that one imports (at the top or inside a
    function), and for a shared group (`register(shared=True)`) the shared operators' module and its
    imports too. Editing any code that computes a group can never serve values computed before the edit."""
    roots = (group.fn.__module__, _OPERATORS) if group.shared else (group.fn.__module__,)
    return _code_version(roots, group.version)


@cache
def _code_version(modules: tuple[str, ...], version: str) -> str:
    h = hashlib.sha256(version.encode())
    for name in dependencies(*modules):
        h.update(name.encode())
        h.update(inspect.getsource(importlib.import_module(name)).encode())
    return h.hexdigest()[:12]


def dependencies(*modules: str) -> list[str]:
    """The `modules` and the meshseg modules they import, transitively, sorted by name. Packages (`__init__`)
    are namespaces here: `from meshseg.features import geometry` depends on `geometry`, not on every family."""
    seen: set[str] = set()
    todo = list(modules)
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        tree = ast.parse(inspect.getsource(importlib.import_module(name)))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                todo.extend(a.name for a in node.names if _is_module(a.name))
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("meshseg"):
                subs = [f"{node.module}.{a.name}" for a in node.names]
                todo.extend(m for m in [node.module, *subs] if _is_module(m))
    return sorted(seen)


def _is_module(name: str) -> bool:
    """A meshseg module with code of its own (not a package)."""
    if not name.startswith("meshseg."):
        return False
    try:
        spec = importlib.util.find_spec(name)
    except ModuleNotFoundError:
        return False
    return spec is not None and spec.submodule_search_locations is None


def cache_key(mesh_hash: str, group: Group, params: dict) -> str:
    blob = json.dumps(
        {"mesh": mesh_hash, "group": group.name, "params": params, "code": code_version(group)},
        sort_keys=True,
        default=repr,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:32]


class FeatureCache:
    """`get(V, F, mesh_hash, group, params, ops)` returns the group's (F, dim) matrix, from disk when it
    can. `root=None` disables the cache (always computes)."""

    def __init__(self, root: str | os.PathLike | None):
        self.root = None if root is None else Path(root).expanduser() / "features"
        if root is not None and Path(root).expanduser().is_file():
            raise ConfigError(f"paths.cache_dir={root} is a file; it must be a folder (or not exist yet)")

    def path(self, mesh_hash: str, group: Group, params: dict) -> Path:
        return self.root / group.name / f"{cache_key(mesh_hash, group, params)}.npz"

    def get(self, V: np.ndarray, F: np.ndarray, mesh_hash: str, group: Group, params: dict, ops=None) -> np.ndarray:
        """`ops`: the mesh's shared `MeshOperators`, used only when the group must be computed."""
        params = group.params(params)
        if self.root is None:
            return group(V, F, ops=ops, **params)
        path = self.path(mesh_hash, group, params)
        if path.exists():
            X = self._load(path, (len(F), group.dim))
            if X is not None:
                return X
        X = group(V, F, ops=ops, **params)
        self._save(path, X)
        return X

    @staticmethod
    def _load(path: Path, shape: tuple[int, int]) -> np.ndarray | None:
        try:
            with np.load(path) as z:
                X = z["x"]
            if X.shape == shape and X.dtype == np.float32:
                return X
            problem = f"shape {X.shape} {X.dtype}, expected {shape} float32"
        except Exception as e:  # any failure to read an entry (zip, npy header, a folder there, ...) is a miss
            problem = f"unreadable ({type(e).__name__}: {e})"
        log.warning("feature cache %s: %s; recomputing", path, problem)
        return None

    @staticmethod
    def _save(path: Path, X: np.ndarray) -> None:
        """Best effort: the values are computed already, so an entry that cannot be written (its temporary file
        deleted by someone clearing the cache, a folder where the file goes) is a warning and a later miss."""
        problem = None
        for _ in range(3):  # the folder may vanish underneath us (a user clearing the cache): recreate it
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write(path, lambda fh: np.savez(fh, x=X))
                return
            except (FileExistsError, NotADirectoryError):
                raise ConfigError(
                    f"paths.cache_dir: cannot write the feature cache under {path.parent}: "
                    "a file stands where a folder is needed"
                ) from None
            except FileNotFoundError as e:
                problem = e
            except OSError as e:
                problem = e
                break
        log.warning("feature cache %s: not written (%s)", path, problem)
