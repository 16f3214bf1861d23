"""Train/test protocols of the paper (§4): leave-one-out, 5-fold, and ShapePFCN's fixed splits."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from meshseg.data.datasets import MeshDataset, normalise_name, sort_ids
from meshseg.data.mesh import MeshDataError
from meshseg.errors import ConfigError


@dataclass(frozen=True)
class Fold:
    index: int
    train: tuple[str, ...]
    test: tuple[str, ...]


def leave_one_out(ids) -> list[Fold]:
    """One fold per mesh: that mesh is the test set, all others train."""
    ids = sort_ids(ids)
    return [Fold(i, tuple(ids[:i] + ids[i + 1 :]), (m,)) for i, m in enumerate(ids)]


def kfold(ids, k: int = 5, seed: int | None = None) -> list[Fold]:
    """Meshes sorted by id and dealt round-robin into k folds (the paper's own lists were never
    published; this is deterministic and balanced to within one mesh). With `seed`, the sorted meshes
    are shuffled by that seed before dealing: another fold assignment, as reproducible."""
    ids = sort_ids(ids)
    if not 2 <= k <= len(ids):
        raise ConfigError(f"{k}-fold split needs between 2 and {len(ids)} folds for {len(ids)} meshes")
    dealt = ids if seed is None else [ids[i] for i in np.random.default_rng(seed).permutation(len(ids))]
    tests = [sort_ids(dealt[i::k]) for i in range(k)]
    return [Fold(i, tuple(m for m in ids if m not in set(t)), tuple(t)) for i, t in enumerate(tests)]


def read_split_file(path: str | os.PathLike) -> dict[str, tuple[tuple[str, ...], tuple[str, ...]]]:
    """Parse ShapePFCN's split file: blocks of `Category NAME`, `Training split: N shapes` + N ids,
    `Test split: N shapes` + N ids. Returns {NAME: (train ids, test ids)} with ids as in the file."""
    try:
        return _parse_split_file(str(path), os.stat(path).st_mtime_ns)
    except OSError as e:
        raise MeshDataError(path, f"cannot read split file: {e.strerror}") from None


@lru_cache(maxsize=4)
def _parse_split_file(path: str, mtime_ns: int) -> dict[str, tuple[tuple[str, ...], tuple[str, ...]]]:
    lines = [line.strip() for line in Path(path).read_text().splitlines()]
    blocks: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {}
    i = 0
    while i < len(lines):
        if not lines[i]:
            i += 1
            continue
        m = re.fullmatch(r"Category\s+(\S+)", lines[i])
        if not m:
            raise MeshDataError(path, f"line {i + 1}: expected 'Category NAME', got {lines[i][:60]!r}")
        name, parts = m.group(1), []
        i += 1
        for part in ("Training", "Test"):
            m = re.fullmatch(part + r" split:\s*(\d+) shapes", lines[i] if i < len(lines) else "")
            if not m:
                raise MeshDataError(path, f"line {i + 1}: expected '{part} split: N shapes' in block {name}")
            n, start = int(m.group(1)), i + 1
            i = start
            while i < len(lines) and lines[i] and not re.match(r"(Category|Training split|Test split)\b", lines[i]):
                i += 1
            if i - start != n:
                raise MeshDataError(
                    path, f"block {name}: {part.lower()} list declares {n} shapes but holds {i - start}"
                )
            parts.append(tuple(lines[start:i]))
        blocks[name] = (parts[0], parts[1])
    return blocks


def fixed(dataset: MeshDataset, category: str, split_file: str | os.PathLike) -> list[Fold]:
    """The single fixed fold of ShapePFCN (Kalogerakis et al. 2017) for one category: block
    `<prefix><Category>` (e.g. psbAirplane), ids `modelNNN` -> mesh NNN."""
    if dataset.split_prefix is None:
        raise ConfigError(f"split=fixed has no lists for dataset {dataset.name!r} (only psb and coseg)")
    blocks = read_split_file(str(split_file))
    key = normalise_name(dataset.split_prefix + category)
    match = [name for name in blocks if normalise_name(name) == key]
    if not match:
        raise MeshDataError(
            split_file,
            f"no block for {dataset.name} category {category!r} (looked for {dataset.split_prefix}{category})",
        )
    train, test = ([re.sub(r"^model", "", s) for s in ids] for ids in blocks[match[0]])
    have = set(dataset.mesh_ids(category))
    missing = sorted(set(train + test) - have)
    if missing:
        raise MeshDataError(
            split_file, f"block {match[0]} names {len(missing)} meshes the dataset lacks: {missing[:8]}"
        )
    return [Fold(0, tuple(sort_ids(train)), tuple(sort_ids(test)))]


class SplitProtocol:
    """A train/test protocol, named by `_target_` in `conf/split/*.yaml`: `folds(dataset, category)`
    gives the checked folds of one category, `name` is the run's `split` tag. A new protocol is a
    subclass with `name` and `make`, and a YAML file naming it."""

    name: str

    def make(self, dataset: MeshDataset, category: str) -> list[Fold]:
        raise NotImplementedError

    def folds(self, dataset: MeshDataset, category: str) -> list[Fold]:
        """The folds of `category`, checked: train and test disjoint, together the category."""
        ids = dataset.mesh_ids(category)
        folds = self.make(dataset, category)
        for fold in folds:
            overlap = set(fold.train) & set(fold.test)
            if overlap:
                raise ConfigError(f"{category} fold {fold.index}: meshes {sorted(overlap)} are in train and test")
            uncovered = set(ids) - set(fold.train) - set(fold.test)
            if uncovered:
                raise ConfigError(
                    f"{category} fold {fold.index}: meshes {sort_ids(uncovered)} are in neither train nor test"
                )
        return folds


class LeaveOneOut(SplitProtocol):
    """One fold per mesh (paper Table 1)."""

    name = "loo"

    def make(self, dataset: MeshDataset, category: str) -> list[Fold]:
        return leave_one_out(dataset.mesh_ids(category))


class KFold(SplitProtocol):
    """Meshes sorted by id and dealt round-robin into k folds (paper Tables 2 and 3); with `seed`,
    shuffled by it first (another fold assignment, to measure how much the fold lists alone move a set)."""

    def __init__(self, k: int = 5, seed: int | None = None):
        if not (isinstance(k, int) and k >= 2):
            raise ConfigError(f"split.k={k} is not allowed: it must be an integer >= 2")
        if not (seed is None or (isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0)):
            raise ConfigError(
                f"split.seed={seed} is not allowed: it must be null (meshes dealt by id) or an integer >= 0"
            )
        self.k, self.seed = k, seed
        self.name = f"{k}fold"

    def make(self, dataset: MeshDataset, category: str) -> list[Fold]:
        return kfold(dataset.mesh_ids(category), self.k, self.seed)


class FixedSplit(SplitProtocol):
    """ShapePFCN's published lists (paper Table 4): one fold per category, from `file`."""

    name = "fixed"

    def __init__(self, file: str | os.PathLike | None = None):
        if not file:
            raise ConfigError("split=fixed needs split.file (ShapePFCN's split list)")
        self.file = file

    def make(self, dataset: MeshDataset, category: str) -> list[Fold]:
        return fixed(dataset, category, self.file)


def build_split(split) -> SplitProtocol:
    """The protocol a split config (`conf/split/*.yaml`) names."""
    from meshseg.instantiate import build

    protocol = build(split, "split")
    if not isinstance(protocol, SplitProtocol):
        raise ConfigError(f"split: {split._target_} is not a meshseg.data.splits.SplitProtocol")
    return protocol


def split_name(split) -> str:
    """A split config's tag: loo, 5fold, fixed."""
    return build_split(split).name


def folds_for(dataset: MeshDataset, category: str, split) -> list[Fold]:
    """The folds a split config (conf/split) gives one category."""
    return build_split(split).folds(dataset, category)
