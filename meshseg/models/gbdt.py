"""Gradient-boosted trees (not in the paper: docs/deviations.md, G1): LightGBM multiclass over per-face
inputs, X^1..X^B concatenated, giving a probability column for every class of the category. The modern
descendant of Kalogerakis et al. 2010's JointBoost, on the same features as every other method.

How many rounds is chosen by early stopping on whole training meshes held out (`inner_meshes` of them,
drawn with the seed), never on faces of a mesh that is also trained on, and never on a test mesh: the
fitter only ever sees the fold's training meshes. With `refit`, the trees are then grown again on every
training mesh for the chosen number of rounds.
"""

from __future__ import annotations

import numpy as np

from meshseg.errors import ConfigError
from meshseg.models.settings import GbdtSettings


def inner_split(groups: np.ndarray, fraction: float, seed: int) -> np.ndarray:
    """The training meshes (values of `groups`) held out for early stopping: round(fraction x meshes), at
    least 1 and leaving at least 1 to train on, drawn by a generator seeded with `seed`; sorted."""
    meshes = np.unique(groups)
    if len(meshes) < 2:
        raise ConfigError("model=gbdt needs at least 2 training meshes: early stopping holds whole meshes out")
    k = min(max(1, round(fraction * len(meshes))), len(meshes) - 1)
    return np.sort(np.random.default_rng([seed, 29]).choice(meshes, size=k, replace=False))


class GradientBoostedTrees:
    """`fit(X, y, groups)` on inputs X (n, ...) flattened to (n, d), `groups` (n,) the mesh of each row;
    `predict_proba(X)` -> (n, n_classes) float32. A class absent from the training faces gets probability 0.
    Deterministic for a given seed and thread count (LightGBM's `deterministic`, row-wise histograms).

    After `fit`: `inner_` the held-out meshes, `rounds_` the rounds early stopping chose, `curve_` the
    held-out multi-class log loss per round. `predict_proba(X, held_out=True)` predicts with the trees
    grown without the held-out meshes (for choosing what comes after the model on them, e.g. the
    refinement's settings); a saved model keeps only the trees it predicts test meshes with."""

    def __init__(self, n_classes: int, n_jobs: int | None = 1, seed: int = 0, **settings):
        """`settings`: GbdtSettings' fields (meshseg/models/settings.py), as conf/model/gbdt.yaml gives them."""
        self.settings = GbdtSettings.of(settings)
        self.n_classes, self.n_jobs, self.seed = int(n_classes), n_jobs, int(seed)

    @property
    def _threads(self) -> int:
        """LightGBM's num_threads for fitting and predicting: n_jobs (trainer.threads), 0 its default."""
        return self.n_jobs if self.n_jobs and self.n_jobs > 0 else 0

    def _params(self, n_present: int) -> dict:
        s = self.settings
        return {
            "objective": "multiclass" if n_present > 2 else "binary",
            **({"num_class": n_present} if n_present > 2 else {}),
            "learning_rate": s.learning_rate,
            "num_leaves": s.num_leaves,
            "min_child_samples": s.min_child_samples,
            "feature_fraction": s.feature_fraction,
            "bagging_fraction": s.bagging_fraction,
            "bagging_freq": 1 if s.bagging_fraction < 1 else 0,
            "lambda_l2": s.lambda_l2,
            "max_bin": s.max_bin,
            "seed": self.seed,
            "deterministic": True,
            "force_row_wise": True,
            "num_threads": self._threads,
            "verbosity": -1,
        }

    def _train(self, X, y, rounds: int, valid=None, bins=None):
        """(booster, evaluation record, its Dataset): `rounds` of boosting, early-stopped on `valid` if given;
        `bins`, a Dataset whose bin edges to reuse (binning 2,400 features again costs more than the rest of
        building the Dataset: benchmarks/gbdt_binning.py)."""
        import lightgbm as lgb

        data = lgb.Dataset(X, y, params={"max_bin": self.settings.max_bin}, reference=bins, free_raw_data=False)
        record: dict = {}
        kwargs = {}
        if valid is not None:
            kwargs["valid_sets"] = [lgb.Dataset(*valid, reference=data)]
            kwargs["callbacks"] = [
                lgb.early_stopping(self.settings.early_stopping_rounds, verbose=False),
                lgb.record_evaluation(record),
            ]
        booster = lgb.train(self._params(self.n_present_), data, num_boost_round=rounds, **kwargs)
        return booster, record, data

    def fit(self, X: np.ndarray, y: np.ndarray, groups: np.ndarray) -> GradientBoostedTrees:
        X = X.reshape(len(X), -1)
        self.classes_ = np.unique(y)
        self.n_present_ = len(self.classes_)
        if self.n_present_ == 1:  # one class: nothing to learn
            self.booster_, self.inner_, self.rounds_, self.curve_ = None, np.array([], int), 0, []
            self.inner_booster_ = None
            return self
        code = np.searchsorted(self.classes_, y)
        self.inner_ = inner_split(groups, self.settings.inner_meshes, self.seed)
        held = np.isin(groups, self.inner_)
        booster, record, data = self._train(X[~held], code[~held], self.settings.max_rounds, (X[held], code[held]))
        self.rounds_ = int(booster.best_iteration or booster.current_iteration())
        self.curve_ = next(iter(next(iter(record.values())).values())) if record else []
        # the refit bins every training row on the edges the rounds were chosen with
        self.booster_ = self._train(X, code, self.rounds_, bins=data)[0] if self.settings.refit else booster
        self.inner_booster_ = booster
        return self

    def predict_proba(self, X: np.ndarray, held_out: bool = False) -> np.ndarray:
        out = np.zeros((len(X), self.n_classes), dtype=np.float32)
        booster = getattr(self, "inner_booster_", None) if held_out else self.booster_
        if held_out and booster is None and self.booster_ is not None:
            raise RuntimeError("the trees grown without the held-out meshes are not kept in a saved model")
        if booster is None:
            out[:, self.classes_[0]] = 1.0
            return out
        p = booster.predict(X.reshape(len(X), -1), num_iteration=self.rounds_, num_threads=self._threads)
        out[:, self.classes_] = p if p.ndim == 2 else np.column_stack([1 - p, p])
        return out

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["inner_booster_"] = None  # used by the run that fits it, not by the saved model
        return state
