"""The training batches of a fold: every training face exactly once per epoch, in an order the seed fixes."""

import numpy as np

from meshseg.training.data import FoldDataModule, Standardiser, TrainSet

N, B, D = 1000, 3, 5


def train_set() -> TrainSet:
    # row i carries i in every entry, so a batch says which faces it holds
    X = np.repeat(np.arange(N, dtype=np.float32)[:, None, None], B, axis=1).repeat(D, axis=2)
    y = np.arange(N, dtype=np.int64) % 4
    return TrainSet(X, y, Standardiser(X), N, 4)


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
