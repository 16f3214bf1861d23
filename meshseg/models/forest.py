"""Random forests (§3.1's CF experiment, §3.3 "AE & RF"): scikit-learn's RandomForestClassifier over
per-face inputs, giving a probability column for every class of the category.

The paper used MATLAB (TreeBagger, 100 trees). TreeBagger's classification defaults are scikit-learn's
too: sqrt(features) candidates per split, leaves of one sample, bootstrap samples, fully grown trees.
"""

from __future__ import annotations

import numpy as np
from sklearn.ensemble import RandomForestClassifier

from meshseg.models.settings import ForestSettings


class RandomForest:
    """`fit(X, y)` on inputs X (n, ...) flattened to (n, d); `predict_proba(X)` -> (n, n_classes) float32.

    A class absent from the training faces gets probability 0 (scikit-learn would drop its column).
    Deterministic for a given seed whatever `n_jobs` is (each tree's seed is drawn up front).
    """

    def __init__(self, n_classes: int, n_jobs: int | None = 1, seed: int = 0, **settings):
        """`settings`: ForestSettings' fields (meshseg/models/settings.py), as conf/model/*.yaml gives them."""
        s = self.settings = ForestSettings.of(settings)
        self.n_classes = int(n_classes)
        self.forest = RandomForestClassifier(
            n_estimators=s.n_estimators,
            max_features=s.max_features,
            min_samples_leaf=s.min_samples_leaf,
            max_depth=s.max_depth,
            bootstrap=s.bootstrap,
            n_jobs=n_jobs,
            random_state=int(seed),
        )

    def fit(self, X: np.ndarray, y: np.ndarray) -> RandomForest:
        self.forest.fit(X.reshape(len(X), -1), y)
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        out = np.zeros((len(X), self.n_classes), dtype=np.float32)
        out[:, self.forest.classes_] = self.forest.predict_proba(X.reshape(len(X), -1))
        return out
