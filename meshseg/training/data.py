"""A fold's data (DESIGN "data flow"): per-mesh feature sets -> multi-scale X^1..X^B -> faces
sampled per training mesh as the budget says -> standardised on the training faces.

Arrays are (faces, branches, features) float32: row u holds X^1(u), ..., X^B(u).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import BatchSampler, DataLoader, Dataset, RandomSampler, Sampler

from meshseg.data.datasets import MeshDataset
from meshseg.data.mesh import Mesh
from meshseg.data.splits import Fold
from meshseg.features.cache import FeatureCache
from meshseg.features.rings import ring_means
from meshseg.features.sets import FeatureSet, check_finite, compute_dataset, parse_entry
from meshseg.timing import Timings


@dataclass
class FeatureSource:
    """A fold's meshes (`fold`: which train, which test) and where their per-face inputs come from: dataset,
    feature set, cache, scales."""

    dataset: MeshDataset
    category: str
    features: FeatureSet
    cache_root: str | None
    branches: int = 3
    ring_adjacency: str = "edge"
    fold: Fold | None = None
    _meshes: dict = field(default_factory=dict, repr=False)  # loaded once per fold (synthetic ones are generated)
    timings: Timings = field(default_factory=Timings, repr=False)  # mesh, load (cache reads), rings (X^k)

    def mesh(self, mesh_id: str) -> Mesh:
        if mesh_id not in self._meshes:
            with self.timings("mesh"):
                self._meshes[mesh_id] = self.dataset.load(self.category, mesh_id)
        return self._meshes[mesh_id]

    def prepare(self, mesh_ids, workers: int = 2) -> int:
        """Compute (in parallel) the features the cache lacks for `mesh_ids`; returns how many meshes."""
        cache = FeatureCache(self.cache_root)
        missing = [m for m in mesh_ids if not self.features.cached(self.mesh(m).content_hash, cache)]
        if missing:
            compute_dataset(
                self.dataset,
                self.features,
                self.cache_root,
                [(self.category, m) for m in missing],
                workers=min(workers, len(missing)),
            )
        return len(missing)

    def load(self, mesh_id: str) -> tuple[Mesh, list[np.ndarray]]:
        """The mesh and its [X^1, ..., X^B], each (faces, features) float32."""
        mesh = self.mesh(mesh_id)
        return mesh, mesh_scales(mesh, self.features, self.cache_root, self.branches, self.ring_adjacency, self.timings)

    def groups(self, mesh: Mesh, names: tuple[str, ...]) -> np.ndarray | None:
        """Other feature groups of a mesh (e.g. a refinement's AGD); see `mesh_groups`."""
        return mesh_groups(mesh, self.features, names, self.cache_root, self.timings)


def mesh_scales(
    mesh: Mesh, features: FeatureSet, cache_root, branches: int, adjacency: str, timings: Timings | None = None
) -> list[np.ndarray]:
    """[X^1, ..., X^B] of any mesh, each (faces, features) float32: its features (cached by the
    mesh's content hash) averaged over the faces <= k-1 steps away."""
    timings = timings or Timings()
    with timings("load"):
        X = features.compute(mesh.vertices, mesh.faces, mesh.content_hash, FeatureCache(cache_root))
        check_finite(X, features, mesh.source)
    with timings("rings"):
        return ring_means(X, mesh.faces, branches, adjacency)


def mesh_groups(
    mesh: Mesh, features: FeatureSet, names: tuple[str, ...], cache_root, timings: Timings | None = None
) -> np.ndarray | None:
    """Feature groups `names` of a mesh (e.g. a refinement's AGD), with the feature set's parameters
    for them and cached like every group; None when `names` is empty."""
    if not names:
        return None
    params = {g: features.params[g] for g in names if g in features.params}
    fs = FeatureSet("+".join(names), tuple(parse_entry(g) for g in names), params)
    with (timings or Timings())("load"):
        X = fs.compute(mesh.vertices, mesh.faces, mesh.content_hash, FeatureCache(cache_root))
        check_finite(X, fs, mesh.source)
    return X


class Standardiser:
    """Per (branch, feature) zero mean and unit variance, fitted on training faces (`fit` sets `mean_` and
    `scale_`, as scikit-learn's StandardScaler). A constant column (e.g. a CF that is identically 0 on a
    category) is centred and left unscaled."""

    def fit(self, X: np.ndarray) -> Standardiser:
        mean = X.mean(axis=0, dtype=np.float64)
        std = column_std(X, mean)
        self.mean_ = mean.astype(np.float32)
        self.scale_ = np.where(std > 1e-12, std, 1.0).astype(np.float32)
        return self

    def transform(self, X: np.ndarray) -> np.ndarray:
        """Standardise in place (X is the caller's fresh array) and return it."""
        X -= self.mean_
        X /= self.scale_
        return X

    def __setstate__(self, state: dict) -> None:
        # the models of older runs (their `model/` artifacts) pickled the fitted state as `mean` and `scale`
        self.__dict__.update({_FITTED.get(k, k): v for k, v in state.items()})


_FITTED = {"mean": "mean_", "scale": "scale_"}


def column_std(X: np.ndarray, mean: np.ndarray, rows: int = 4096) -> np.ndarray:
    """`X.std(axis=0, dtype=np.float64)` bit for bit, given `X.mean(axis=0, dtype=np.float64)`, in blocks of
    `rows`: numpy makes an (n, ...) float64 temporary of the deviations (4.8 GB for a GBDT 16k training set,
    twice X). numpy sums axis 0 one row after the other, so each block's sum starting from the running total
    (its first row) continues the very same sum; the first starts from 0, which adds exactly."""
    flat, centre = X.reshape(len(X), -1), mean.reshape(-1)
    block = np.zeros((rows + 1, flat.shape[1]))
    for start in range(0, len(flat), rows):
        part = flat[start : start + rows]
        deviations = block[1 : len(part) + 1]
        np.subtract(part, centre, out=deviations)
        np.multiply(deviations, deviations, out=deviations)
        block[0] = np.add.reduce(block[: len(part) + 1], axis=0)
    return np.sqrt(block[0] / len(flat)).reshape(mean.shape)


@dataclass
class TrainSet:
    X: np.ndarray  # (n, branches, features) float32, standardised
    y: np.ndarray  # (n,) int64
    standardiser: Standardiser
    mesh_faces: int  # faces of the training meshes before sampling
    n_classes: int  # the category's labels (a class may have no training face)
    #: budget.resample=epoch: epoch e trains on rows epoch_rows[e] of X (X holds every face any epoch
    #: draws); None: every epoch trains on all of X
    epoch_rows: tuple[np.ndarray, ...] | None = None
    #: (n,) the training mesh each row comes from, as its position in the fold's training list (a fitter that
    #: holds meshes out of its training faces, as gbdt's early stopping does, splits by it)
    mesh_index: np.ndarray | None = None
    mesh_ids: tuple[str, ...] = ()  # the fold's training meshes, in that order
    #: (n,) each row's face within its mesh, and where the meshes came from: a fitter that needs whole training
    #: meshes (a stacked second stage predicts every face of them) reads them back from the source
    faces: np.ndarray | None = None
    source: FeatureSource | None = field(default=None, repr=False)

    @property
    def samples_per_epoch(self) -> int:
        return len(self.y) if self.epoch_rows is None else len(self.epoch_rows[0])

    def of_meshes(self, keep) -> TrainSet:
        """The rows of the training meshes at positions `keep` (in `mesh_ids`), renumbered in that order, with
        the same standardiser (fitted on every training mesh's faces: their inputs, never their labels)."""
        keep = [int(i) for i in keep]
        if self.epoch_rows is not None:
            raise ValueError("of_meshes: rows drawn per epoch (budget.resample=epoch) cannot be split by mesh")
        rows = np.isin(self.mesh_index, keep)
        index = np.full(len(self.mesh_ids), -1, dtype=np.int32)
        index[keep] = np.arange(len(keep), dtype=np.int32)
        return replace(
            self,
            X=self.X[rows],
            y=self.y[rows],
            mesh_faces=sum(self.source.mesh(self.mesh_ids[i]).n_faces for i in keep) if self.source else 0,
            mesh_index=index[self.mesh_index[rows]],
            mesh_ids=tuple(self.mesh_ids[i] for i in keep),
            faces=None if self.faces is None else self.faces[rows],
        )


def sample_faces(n_faces: int, per_mesh: int | None, rng: np.random.Generator) -> np.ndarray:
    """Uniformly sampled face indices (sorted, without replacement); all faces if `per_mesh` is None
    or at least the mesh's face count."""
    if per_mesh is None or per_mesh >= n_faces:
        return np.arange(n_faces)
    return np.sort(rng.choice(n_faces, size=per_mesh, replace=False))


def epoch_samples(n_faces: int, per_mesh: int | None, epochs: int, seed: int, mesh_index: int) -> list[np.ndarray]:
    """budget.resample=epoch: one uniform sample of `per_mesh` faces (sorted, without replacement) for
    each epoch, drawn afresh from a generator seeded by (seed, mesh, epoch), so a resumed fold draws what
    an uninterrupted one does; every face each epoch where `per_mesh` is None or covers the mesh."""
    return [
        sample_faces(n_faces, per_mesh, np.random.default_rng([seed, mesh_index, epoch])) for epoch in range(epochs)
    ]


def build_train(
    source: FeatureSource, mesh_ids, faces_per_mesh: int | None, seed: int, epochs: int | None = None
) -> TrainSet:
    """Sampled faces of every training mesh, all branches, standardised on themselves. With `epochs`
    (budget.resample=epoch), each epoch gets its own sample of `faces_per_mesh` faces per mesh: X holds
    the union of the epochs' samples (standardised on it) and `epoch_rows` says which rows each trains on."""
    rng = np.random.default_rng(seed)
    xs, ys, which, faces, total, per_epoch, offset = [], [], [], [], 0, [[] for _ in range(epochs or 0)], 0
    for i, mesh_id in enumerate(mesh_ids):
        mesh, scales = source.load(mesh_id)
        if epochs is None:
            idx = sample_faces(mesh.n_faces, faces_per_mesh, rng)
        else:
            drawn = epoch_samples(mesh.n_faces, faces_per_mesh, epochs, seed, i)
            idx = np.unique(np.concatenate(drawn))
            for rows, d in zip(per_epoch, drawn):
                rows.append(offset + np.searchsorted(idx, d))
            offset += len(idx)
        xs.append(np.stack([X[idx] for X in scales], axis=1))
        ys.append(mesh.labels[idx])
        faces.append(idx)
        which.append(np.full(len(idx), i, dtype=np.int32))
        total += mesh.n_faces
    with source.timings("standardise"):
        X = np.concatenate(xs)
        xs.clear()  # the per-mesh copies: no second X in memory while standardising
        standardiser = Standardiser().fit(X)
        X = standardiser.transform(X)
    n_classes = len(source.dataset.label_names(source.category))
    epoch_rows = None if epochs is None else tuple(np.concatenate(rows) for rows in per_epoch)
    y = np.concatenate(ys).astype(np.int64)
    return TrainSet(
        X,
        y,
        standardiser,
        total,
        n_classes,
        epoch_rows,
        np.concatenate(which),
        tuple(mesh_ids),
        np.concatenate(faces),
        source,
    )


def iter_test_inputs(source: FeatureSource, mesh_ids, standardiser: Standardiser) -> Iterator[tuple[Mesh, np.ndarray]]:
    """Each test mesh with its full (faces, branches, features) input, standardised with the
    training statistics; one mesh in memory at a time."""
    for mesh_id in mesh_ids:
        mesh, scales = source.load(mesh_id)
        with source.timings("standardise"):
            X = standardiser.transform(np.stack(scales, axis=1))
        yield mesh, X


class _Rows(Dataset):
    """Indexable by a list of rows: one fancy-index per batch instead of one per sample."""

    def __init__(self, X: np.ndarray, y: np.ndarray):
        self.X, self.y = torch.from_numpy(X), torch.from_numpy(y)

    def __len__(self) -> int:
        return len(self.y)

    def __getitem__(self, rows):
        return self.X[rows], self.y[rows]


class EpochBatches(Sampler):
    """Mini-batches of the rows drawn for the current epoch (budget.resample=epoch), shuffled by a
    generator seeded with (seed, epoch). Lightning calls `set_epoch` before each epoch."""

    def __init__(self, epoch_rows: tuple[np.ndarray, ...], batch_size: int, seed: int):
        self.epoch_rows, self.batch_size, self.seed, self.epoch = epoch_rows, batch_size, seed, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return -(-len(self.epoch_rows[0]) // self.batch_size)

    def __iter__(self) -> Iterator[list[int]]:
        rows = self.epoch_rows[self.epoch % len(self.epoch_rows)]
        order = rows[
            torch.randperm(len(rows), generator=torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)).numpy()
        ]
        for i in range(0, len(order), self.batch_size):
            yield order[i : i + self.batch_size].tolist()


class FoldDataModule(pl.LightningDataModule):
    """The training faces of one fold, shuffled each epoch with a seeded generator (with
    budget.resample=epoch, the rows of each epoch's own sample)."""

    def __init__(self, train: TrainSet, batch_size: int, seed: int):
        super().__init__()
        self.train, self.batch_size, self.seed = train, int(batch_size), int(seed)

    def train_dataloader(self) -> DataLoader:
        rows = _Rows(self.train.X, self.train.y)
        if self.train.epoch_rows is not None:
            return DataLoader(
                rows, sampler=EpochBatches(self.train.epoch_rows, self.batch_size, self.seed), batch_size=None
            )
        order = RandomSampler(rows, generator=torch.Generator().manual_seed(self.seed))
        return DataLoader(rows, sampler=BatchSampler(order, self.batch_size, drop_last=False), batch_size=None)
