"""Datasets: L-PSB, COSEG and the embedded synthetic set, behind one small interface.

A dataset has categories; a category has meshes (ids sorted numerically where they are numbers)
and one label vocabulary shared by all its meshes. `load(category, id)` returns a validated Mesh.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterator
from functools import cached_property
from pathlib import Path

import numpy as np

from meshseg.data import sdf, synthetic
from meshseg.data.archive import file_sha256, is_archive, resolve_root
from meshseg.data.io import read_off, read_psb_label_names, read_psb_labels, read_seg
from meshseg.data.mesh import Mesh, MeshDataError
from meshseg.errors import ConfigError


def sort_ids(ids) -> list[str]:
    """Numeric ids in numeric order ("2" < "10"), others after them alphabetically."""
    return sorted(ids, key=lambda s: (0, int(s), "") if s.isdigit() else (1, 0, s))


def normalise_name(name: str) -> str:
    """Compare category names across sources: 'tele-aliens' == 'TeleAliens'."""
    return re.sub(r"[^a-z0-9]", "", name.lower())


def build_dataset(cfg) -> MeshDataset:
    """Instantiate `cfg.dataset`-style config; errors surface as themselves, not Hydra's wrapper."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    try:
        return instantiate(cfg)
    except InstantiationException as e:
        raise (e.__cause__ or e) from None


class MeshDataset:
    """What every dataset provides; subclasses fill `categories`, `mesh_ids`, `label_names`, `load`."""

    name: str = ""
    #: prefix of this dataset's blocks in the ShapePFCN split file ('psb', 'coseg'); None: no fixed split
    split_prefix: str | None = None

    categories: list[str]

    def mesh_ids(self, category: str) -> list[str]:
        raise NotImplementedError

    def label_names(self, category: str) -> tuple[str, ...]:
        raise NotImplementedError

    def load(self, category: str, mesh_id: str) -> Mesh:
        raise NotImplementedError

    @property
    def data_hash(self) -> str:
        raise NotImplementedError

    @property
    def source(self) -> str:
        """Where its meshes are read from: its root folder, or the generator for synthetic data."""
        root = getattr(self, "root", None)
        return str(Path(root).absolute()) if root is not None else f"meshseg.data.synthetic ({self.name})"

    def check_category(self, category: str) -> str:
        if category not in self.categories:
            raise ConfigError(f"dataset {self.name!r} has no category {category!r}; it has {self.categories}")
        return category

    def meshes(self, category: str) -> Iterator[Mesh]:
        for mesh_id in self.mesh_ids(category):
            yield self.load(category, mesh_id)


class _FileDataset(MeshDataset):
    """A dataset read from a folder or archive of files."""

    def __init__(self, root: str, cache_dir: str = ".cache"):
        if root is None:
            raise MeshDataError(
                f"dataset {self.name}", "dataset.root is not set: pass dataset.root=PATH (a folder or an archive)"
            )
        self.given_root = Path(root).expanduser()
        self.root = resolve_root(self.given_root, cache_dir)

    @cached_property
    def data_hash(self) -> str:
        """Content hash of the archive, or of every file under the folder."""
        if is_archive(self.given_root):
            return file_sha256(self.given_root)[:16]
        h = hashlib.sha256()
        for p in sorted(self.root.rglob("*")):
            if p.is_file():
                h.update(str(p.relative_to(self.root)).encode())
                h.update(file_sha256(p).encode())
        return h.hexdigest()[:16]


def _find_dir(root: Path, is_root, what: str) -> Path:
    """`root` or the one folder inside it (an archive's top folder) that `is_root` accepts."""
    for candidate in [root, *sorted(p for p in root.iterdir() if p.is_dir())]:
        if is_root(candidate):
            return candidate
    raise MeshDataError(root, f"no {what} found here")


class PSB(_FileDataset):
    """Labelled Princeton Segmentation Benchmark: `<Category>/<id>.off` + `<id>_labels.txt`."""

    name = "psb"
    split_prefix = "psb"

    def __init__(self, root: str, cache_dir: str = ".cache"):
        super().__init__(root, cache_dir)
        self.root = _find_dir(
            self.root, lambda d: any(d.glob("*/*_labels.txt")), "L-PSB category folders (<Category>/<id>_labels.txt)"
        )
        self.categories = sorted(d.name for d in self.root.iterdir() if d.is_dir() and any(d.glob("*.off")))
        self._vocab: dict[str, tuple[str, ...]] = {}

    def mesh_ids(self, category: str) -> list[str]:
        return sort_ids(p.stem for p in (self.root / self.check_category(category)).glob("*.off"))

    def label_names(self, category: str) -> tuple[str, ...]:
        """Sorted union of the label names of all the category's meshes."""
        if category not in self._vocab:
            names: set[str] = set()
            for mesh_id in self.mesh_ids(category):
                names.update(read_psb_label_names(self._labels_path(category, mesh_id)))
            self._vocab[category] = tuple(sorted(names))
        return self._vocab[category]

    def _labels_path(self, category: str, mesh_id: str) -> Path:
        path = self.root / category / f"{mesh_id}_labels.txt"
        if not path.is_file():
            raise MeshDataError(path, "labels file missing for this mesh")
        return path

    def load(self, category: str, mesh_id: str) -> Mesh:
        path = self.root / self.check_category(category) / f"{mesh_id}.off"
        v, f = read_off(path)
        labels_path = self._labels_path(category, mesh_id)
        local, names = read_psb_labels(labels_path, len(f))
        vocab = self.label_names(category)
        to_vocab = np.array([vocab.index(n) for n in names], np.int64)
        return Mesh(v, f, to_vocab[local], vocab, id=mesh_id, category=category, source=str(path))


class COSEG(_FileDataset):
    """COSEG sets: any folder holding `shapes/<id>.off` and `gt/<id>.seg` is a category."""

    name = "coseg"
    split_prefix = "coseg"

    def __init__(self, root: str, cache_dir: str = ".cache"):
        super().__init__(root, cache_dir)
        dirs = [self.root, *self.root.glob("*"), *self.root.glob("*/*")]
        self._dirs = {d.name: d for d in sorted(dirs) if (d / "shapes").is_dir() and (d / "gt").is_dir()}
        if not self._dirs:
            raise MeshDataError(self.root, "no COSEG set found (a folder with shapes/ and gt/)")
        self.categories = sorted(self._dirs)
        self._vocab: dict[str, tuple[int, ...]] = {}

    def mesh_ids(self, category: str) -> list[str]:
        shapes = self._dirs[self.check_category(category)] / "shapes"
        ids = sort_ids(p.stem for p in shapes.glob("*.off"))
        if not ids:  # else every split fails later with a message that does not name the set
            raise MeshDataError(shapes, f"COSEG set {category!r} has no shapes (*.off)")
        return ids

    def _seg_path(self, category: str, mesh_id: str) -> Path:
        path = self._dirs[category] / "gt" / f"{mesh_id}.seg"
        if not path.is_file():
            raise MeshDataError(path, "labels file missing for this mesh")
        return path

    def _label_values(self, category: str) -> tuple[int, ...]:
        if category not in self._vocab:
            values: set[int] = set()
            for mesh_id in self.mesh_ids(category):
                values.update(np.unique(read_seg(self._seg_path(category, mesh_id))).tolist())
            self._vocab[category] = tuple(sorted(values))
        return self._vocab[category]

    def label_names(self, category: str) -> tuple[str, ...]:
        """COSEG labels are integers; their names are those integers, sorted."""
        return tuple(str(v) for v in self._label_values(category))

    def load(self, category: str, mesh_id: str) -> Mesh:
        path = self._dirs[self.check_category(category)] / "shapes" / f"{mesh_id}.off"
        v, f = read_off(path)
        seg = read_seg(self._seg_path(category, mesh_id), len(f))
        values = np.asarray(self._label_values(category))
        labels = np.searchsorted(values, seg)
        return Mesh(v, f, labels, self.label_names(category), id=mesh_id, category=category, source=str(path))


class Synthetic(MeshDataset):
    """Embedded procedurally generated labelled meshes: needs no download, learnable by design."""

    name = "synthetic"

    def __init__(
        self,
        categories: list[str] | None = None,
        meshes_per_category: int = 20,
        seed: int = 0,
        min_faces: int = 1500,
        max_faces: int = 6000,
    ):
        categories = list(categories or synthetic.CATEGORIES)
        unknown = sorted(set(categories) - set(synthetic.CATEGORIES))
        if unknown:
            raise ConfigError(f"synthetic dataset has no categories {unknown}; it has {list(synthetic.CATEGORIES)}")
        self.categories = categories
        self.meshes_per_category = int(meshes_per_category)
        self.seed, self.min_faces, self.max_faces = int(seed), int(min_faces), int(max_faces)

    def mesh_ids(self, category: str) -> list[str]:
        self.check_category(category)
        return [str(i) for i in range(self.meshes_per_category)]

    def label_names(self, category: str) -> tuple[str, ...]:
        return synthetic.PART_NAMES[self.check_category(category)]

    def load(self, category: str, mesh_id: str) -> Mesh:
        if mesh_id not in self.mesh_ids(category):
            raise ConfigError(
                f"synthetic category {category!r} has no mesh {mesh_id!r}; ids are 0..{self.meshes_per_category - 1}"
            )
        v, f, labels = synthetic.generate(category, int(mesh_id), self.seed, self.min_faces, self.max_faces)
        return Mesh(
            v,
            f,
            labels,
            self.label_names(category),
            id=mesh_id,
            category=category,
            source=f"synthetic:{category}/{mesh_id}?seed={self.seed}",
        )

    @property
    def data_hash(self) -> str:
        """Parameters plus the generator's source (its shapes' distances too): changing either names new data."""
        h = hashlib.sha256(Path(synthetic.__file__).read_bytes() + Path(sdf.__file__).read_bytes())
        h.update(repr((self.categories, self.meshes_per_category, self.seed, self.min_faces, self.max_faces)).encode())
        return h.hexdigest()[:16]
