"""Feature sets: an ordered list of groups (or column slices of groups) and their column layout.

`f800` is the paper's vector (593 Kalogerakis + CF0 + CF1..5 + GC + HKS + SIHKS), `f600` the same
without HKS and SIHKS, and `cf0`, `cf1`, `cf0_1`, `cf1_5`, `cf0_5` the CF ablations of the paper's
CF figure. Entries are written `group` or `group[a:b]` (columns a..b-1 of that group).
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass, field

import numpy as np

from meshseg.data.datasets import MeshDataset
from meshseg.errors import ConfigError, MeshDataError
from meshseg.features.cache import FeatureCache
from meshseg.features.operators import MeshOperators
from meshseg.features.registry import get_group
from meshseg.timing import time_left

log = logging.getLogger(__name__)

_ENTRY = re.compile(r"^(\w+)(?:\[(\d*):(\d*)\])?$")


@dataclass(frozen=True)
class Entry:
    group: str
    start: int
    stop: int

    @property
    def label(self) -> str:
        g = get_group(self.group)
        return self.group if (self.start, self.stop) == (0, g.dim) else f"{self.group}[{self.start}:{self.stop}]"


def parse_entry(text: str) -> Entry:
    m = _ENTRY.match(text.strip())
    if not m:
        raise ConfigError(f"bad feature set entry {text!r}: expected 'group' or 'group[a:b]'")
    group = get_group(m.group(1))
    start = int(m.group(2) or 0)
    stop = int(m.group(3) or group.dim)
    if not 0 <= start < stop <= group.dim:
        raise ConfigError(f"feature set entry {text!r}: columns {start}:{stop} outside 0:{group.dim}")
    return Entry(group.name, start, stop)


@dataclass(frozen=True)
class FeatureSet:
    name: str
    entries: tuple[Entry, ...]
    params: dict = field(default_factory=dict)  # {group: {param: value}} overrides

    @classmethod
    def from_config(cls, cfg) -> FeatureSet:
        """From a `conf/features/*.yaml` node: name, groups (entries), params."""
        params = {k: dict(v) for k, v in dict(cfg.get("params") or {}).items()}
        entries = tuple(parse_entry(e) for e in cfg.groups)
        for group in params:
            get_group(group).params(params[group])  # unknown group or parameter: fail now
        return cls(cfg.name, entries, params)

    @property
    def dim(self) -> int:
        return sum(e.stop - e.start for e in self.entries)

    @property
    def layout(self) -> dict[str, tuple[int, int]]:
        """Entry label -> (first column, one past the last column) in this set's matrix."""
        out, at = {}, 0
        for e in self.entries:
            out[e.label] = (at, at + e.stop - e.start)
            at += e.stop - e.start
        return out

    @property
    def columns(self) -> list[str]:
        return [name for e in self.entries for name in get_group(e.group).columns[e.start : e.stop]]

    def group_params(self, group: str) -> dict:
        return get_group(group).params(self.params.get(group))

    def cached(self, mesh_hash: str, cache: FeatureCache) -> bool:
        """Whether every group of this set is already in `cache` for that mesh."""
        return cache.root is not None and all(
            cache.path(mesh_hash, get_group(g), self.group_params(g)).exists() for g in {e.group for e in self.entries}
        )

    def compute(
        self,
        V: np.ndarray,
        F: np.ndarray,
        mesh_hash: str,
        cache: FeatureCache | None = None,
        timings: dict | None = None,
    ) -> np.ndarray:
        """The (F, dim) float32 matrix; each group computed once (or read from the cache).
        `timings`, if given, receives seconds per group (a group that shares operators is charged
        for the ones it computes first: `hks` for the eigen-solve that `sihks` then reuses)."""
        cache = cache or FeatureCache(None)
        # one per call: the groups computed here share its eigenpairs and geodesics, and they are
        # freed with it (only those of a group not already on disk are ever computed)
        ops = MeshOperators(V, F, key=mesh_hash)
        blocks: dict[str, np.ndarray] = {}
        for e in self.entries:
            if e.group not in blocks:
                t0 = time.perf_counter()
                blocks[e.group] = cache.get(V, F, mesh_hash, get_group(e.group), self.params.get(e.group, {}), ops)
                if timings is not None:
                    timings[e.group] = time.perf_counter() - t0
        return np.ascontiguousarray(
            np.concatenate([blocks[e.group][:, e.start : e.stop] for e in self.entries], axis=1)
        )


def check_finite(X: np.ndarray, fs: FeatureSet, source: str) -> None:
    """One rule for every command: a mesh whose features are not all finite is refused, naming the
    mesh and the first columns at fault, never written or trained on."""
    if not np.isfinite(X).all():
        bad = [fs.columns[j] for j in np.flatnonzero(~np.isfinite(X).all(axis=0))]
        rows = int((~np.isfinite(X).all(axis=1)).sum())
        raise MeshDataError(
            source,
            f"{rows} faces have non-finite {fs.name} features, in columns {bad[:5]}"
            f"{' …' if len(bad) > 5 else ''} (degenerate faces or unused vertices?)",
        )


def _one(dataset: MeshDataset, category: str, mesh_id: str, fs: FeatureSet, cache_root: str | None):
    t0 = time.perf_counter()
    mesh = dataset.load(category, mesh_id)
    X = fs.compute(mesh.vertices, mesh.faces, mesh.content_hash, FeatureCache(cache_root))
    check_finite(X, fs, mesh.source)
    return category, mesh_id, mesh.n_faces, time.perf_counter() - t0


def compute_dataset(
    dataset: MeshDataset,
    fs: FeatureSet,
    cache_root: str | None,
    jobs: list[tuple[str, str]],
    workers: int = 2,
) -> tuple[int, int, float]:
    """Features of the meshes `jobs` ((category, mesh id) pairs), `workers` meshes at a time, into the
    cache; one log line per mesh (k/N, with the time left at the pace so far), then the total."""
    from joblib import Parallel, delayed

    t0 = time.perf_counter()
    n_faces = 0
    results = Parallel(n_jobs=workers, return_as="generator_unordered")(
        delayed(_one)(dataset, c, m, fs, cache_root) for c, m in jobs
    )
    for k, (category, mesh_id, faces, seconds) in enumerate(results, 1):
        n_faces += faces
        left = time_left(time.perf_counter() - t0, k, len(jobs) - k)
        log.info(
            "features %d/%d: %s/%s, %d faces in %.1f s (%.0f faces/s); %s",
            *(k, len(jobs), category, mesh_id, faces, seconds, faces / seconds, left),
        )
    elapsed = time.perf_counter() - t0
    log.info("features: %d meshes, %d faces, %.0f faces/s", len(jobs), n_faces, n_faces / elapsed)
    return len(jobs), n_faces, elapsed
