"""The training batches of a fold: every training face exactly once per epoch, in an order the seed fixes."""

import numpy as np

from meshseg.training.data import FoldDataModule, Standardiser, TrainSet, column_std

N, B, D = 1000, 3, 5


def train_set() -> TrainSet:
    # row i carries i in every entry, so a batch says which faces it holds
    X = np.repeat(np.arange(N, dtype=np.float32)[:, None, None], B, axis=1).repeat(D, axis=2)
    y = np.arange(N, dtype=np.int64) % 4
    return TrainSet(X, y, Standardiser().fit(X), N, 4)


def epochs(seed: int, n: int = 3, batch_size: int = 128) -> list[list[np.ndarray]]:
    loader = FoldDataModule(train_set(), batch_size, seed).train_dataloader()
    return [[x[:, 0, 0].numpy().astype(int) for x, _ in loader] for _ in range(n)]


def test_every_face_once_per_epoch_in_a_seeded_order():
    first = epochs(seed=7)
    for batches in first:
        assert [len(b) for b in batches] == [128] * 7 + [N - 7 * 128]  # full batches, the rest last
        order = np.concatenate(batches)
        assert np.array_equal(np.sort(order), np.arange(N))  # each face exactly once
        assert not np.array_equal(order, np.arange(N))  # shuffled
    orders = [np.concatenate(b) for b in first]
    assert not np.array_equal(orders[0], orders[1])  # a new order each epoch ...
    again = [np.concatenate(b) for b in epochs(seed=7)]
    assert all(np.array_equal(a, b) for a, b in zip(orders, again))  # ... the same ones for the same seed
    other = [np.concatenate(b) for b in epochs(seed=8)]
    assert not np.array_equal(orders[0], other[0])


def test_labels_travel_with_their_faces():
    loader = FoldDataModule(train_set(), 64, 0).train_dataloader()
    for x, y in loader:
        rows = x[:, 0, 0].numpy().astype(int)
        assert np.array_equal(y.numpy(), rows % 4) and y.dtype.is_floating_point is False


# budget.resample=epoch: a fresh seeded sample of faces per mesh every epoch


class _Source:
    """Two meshes of 300 and 40 faces; feature value = 1000 * mesh + face, label = face % 3."""

    category = "c"

    class dataset:
        @staticmethod
        def label_names(category):
            return ["a", "b", "c"]

    def __init__(self):
        from meshseg.timing import Timings

        self.timings = Timings()
        self.sizes = {"m0": 300, "m1": 40}

    def load(self, mesh_id):
        from types import SimpleNamespace

        n, k = self.sizes[mesh_id], int(mesh_id[1])
        X = (1000 * k + np.arange(n, dtype=np.float32))[:, None].repeat(D, axis=1)
        return SimpleNamespace(n_faces=n, labels=np.arange(n) % 3), [X, X + 0.5]


def test_each_epoch_draws_its_own_seeded_sample_of_faces():
    from meshseg.training.data import epoch_samples

    draws = epoch_samples(300, 50, epochs=6, seed=3, mesh_index=0)
    assert [len(d) for d in draws] == [50] * 6
    assert all(len(np.unique(d)) == 50 and d.min() >= 0 and d.max() < 300 for d in draws)  # no repeat in an epoch
    assert len({tuple(d) for d in draws}) == 6  # a different sample every epoch
    assert all(np.array_equal(a, b) for a, b in zip(draws, epoch_samples(300, 50, 6, 3, 0)))  # reproducible
    assert not np.array_equal(draws[0], epoch_samples(300, 50, 6, 4, 0)[0])  # another seed, another draw
    assert not np.array_equal(draws[0], epoch_samples(300, 50, 6, 3, 1)[0])  # another mesh, another draw
    # every face, every epoch, where the budget takes all faces or more than the mesh has
    assert all(np.array_equal(d, np.arange(40)) for d in epoch_samples(40, None, 3, 0, 0))
    assert all(np.array_equal(d, np.arange(40)) for d in epoch_samples(40, 50, 3, 0, 0))


def test_the_train_set_holds_every_epochs_faces_and_which_rows_each_epoch_trains_on():
    from meshseg.training.data import build_train, epoch_samples

    train = build_train(_Source(), ["m0", "m1"], 50, seed=3, epochs=4)
    raw = train.standardiser.mean_[0, 0] + train.X[:, 0, 0] * train.standardiser.scale_[0, 0]  # undo standardising
    for e, rows in enumerate(train.epoch_rows):
        want = np.concatenate([epoch_samples(300, 50, 4, 3, 0)[e], 1000 + np.arange(40)])
        assert np.allclose(np.sort(raw[rows]), np.sort(want), atol=1e-2)  # 50 of m0's faces, all 40 of m1's
        assert np.array_equal(train.y[rows], np.round(raw[rows]).astype(int) % 1000 % 3)  # labels travel along
    assert train.samples_per_epoch == 90 and len(np.unique(np.round(raw))) == len(raw)  # each face held once
    assert 90 < len(train.y) <= 4 * 50 + 40
    once = build_train(_Source(), ["m0", "m1"], 50, seed=3)  # resample=fold: one sample, no epoch rows
    assert once.epoch_rows is None and once.samples_per_epoch == len(once.y) == 90


def test_training_sees_each_epochs_own_sample():
    """Through Lightning: epoch e's batches hold exactly the rows drawn for epoch e (Lightning tells the
    sampler the epoch), shuffled, and the same again for the same seed."""
    import pytorch_lightning as pl
    import torch

    from meshseg.training.context import TrainContext
    from meshseg.training.loop import train_stage

    rows = tuple(np.sort(np.random.default_rng(e).choice(N, 100, replace=False)) for e in range(3))
    base = train_set()
    train = TrainSet(base.X, base.y, base.standardiser, N, 4, rows)

    class Record(pl.LightningModule):
        def __init__(self):
            super().__init__()
            self.w, self.seen = torch.nn.Parameter(torch.zeros(1)), []

        def training_step(self, batch, i):
            if i == 0:
                self.seen.append([])
            self.seen[-1].append(batch[0][:, 0, 0].numpy().astype(int))
            return (self.w**2).sum()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    def fit(seed):
        module = Record()
        train_stage(module, train, TrainContext(epochs=3, batch_size=32, seed=seed))
        return [np.concatenate(s) for s in module.seen]

    seen = fit(5)
    assert len(seen) == 3
    for e, order in enumerate(seen):
        assert np.array_equal(np.sort(order), rows[e]) and not np.array_equal(order, rows[e])
    assert all(np.array_equal(a, b) for a, b in zip(seen, fit(5)))


def test_resampling_each_epoch_is_refused_for_a_fitter_that_fits_once():
    import pytest

    from meshseg.errors import ConfigError
    from meshseg.training.context import TrainContext
    from meshseg.training.fitters import ForestFitter, NetFitter

    ctx = TrainContext(epochs=2, batch_size=8, resample="epoch")
    with pytest.raises(ConfigError, match=r"budget.resample=epoch is not allowed with ForestFitter"):
        ForestFitter({"n_estimators": 2}, ctx)
    NetFitter(lambda **kw: None, {}, ctx)  # a network trains epoch by epoch: allowed


def test_standardiser_fits_like_a_scikit_learn_scaler():
    rng = np.random.default_rng(0)
    X = (rng.standard_normal((200, B, D)) * 3 + 1).astype(np.float32)
    X[:, 1, 2] = 5.0  # a constant column: centred, not scaled
    s = Standardiser().fit(X)
    assert s.mean_.dtype == s.scale_.dtype == np.float32 and s.mean_.shape == (B, D)
    Z = s.transform(X.copy())
    np.testing.assert_allclose(Z.reshape(-1, B * D).mean(0), 0, atol=1e-5)
    std = Z.std(0)
    assert std[1, 2] == 0 and np.allclose(np.delete(std.ravel(), 1 * D + 2), 1, atol=1e-4)
    Y = X.copy()
    assert s.transform(Y) is Y  # in place


def test_the_standardiser_sums_in_float64_in_blocks_of_rows():
    """The numbers of the shipped runs (statistics of a float64 copy, bit for bit) without a float64 array the
    size of X: numpy reports its buffers to tracemalloc, and its own X.std(dtype=float64) would take 2x X."""
    import tracemalloc

    rng = np.random.default_rng(1)
    X = (rng.standard_normal((20000, 3, 100)) * rng.uniform(1e-3, 1e3, (3, 100)) + 40).astype(np.float32)
    tracemalloc.start()
    s = Standardiser().fit(X)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    X64 = X.astype(np.float64)
    std = X64.std(axis=0)
    np.testing.assert_array_equal(s.mean_, X64.mean(axis=0).astype(np.float32))
    np.testing.assert_array_equal(s.scale_, np.where(std > 1e-12, std, 1.0).astype(np.float32))
    assert peak < 0.5 * X.nbytes, peak / X.nbytes  # one block of rows in float64 (10 MB here), not 2x X


def test_the_blocked_deviation_equals_numpys_bit_for_bit_whatever_the_block():
    rng = np.random.default_rng(2)
    X = (rng.standard_normal((1001, 2, 50)) * rng.uniform(1e-2, 1e4, (2, 50)) - 7e3).astype(np.float32)
    X[:, 0, 3] = 2.5  # a constant column: 0 exactly
    mean = X.mean(axis=0, dtype=np.float64)
    for rows in (1, 7, 1000, 1001, 5000):
        np.testing.assert_array_equal(column_std(X, mean, rows), X.std(axis=0, dtype=np.float64))
    assert column_std(X, mean, 7)[0, 3] == 0.0


def test_a_standardiser_pickled_by_older_runs_still_transforms():
    """The `model/` artifacts of older runs hold Standardisers whose fitted state is named `mean`, `scale`."""
    import pickle

    old = Standardiser.__new__(Standardiser)
    old.__dict__.update(mean=np.float32([1, 2]), scale=np.float32([2, 4]))
    loaded = pickle.loads(pickle.dumps(old))
    np.testing.assert_array_equal(loaded.transform(np.float32([[3, 6]])), [[1, 1]])
    assert sorted(vars(loaded)) == ["mean_", "scale_"]
