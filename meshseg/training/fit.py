"""Train one fold and predict every face of its test meshes.

The model config's `kind` says how a model is fitted (default `net`):

* `net`: one network, `net._target_` + its arguments (cnn1d, cnn2d, pca_nn), trained by `Segmenter`
  with `optim`; a network with frozen data-fitted layers (pca_nn's PCA) has them fitted first, on the
  training faces, by its `fit_frozen`;
* `autoencoder`: stacked autoencoders, then `head: softmax` (ae_nn) or `head: forest` (ae_rf)
  (`meshseg.training.stages.fit_autoencoder`);
* `forest`: a random forest on the features (rf) (`meshseg.training.stages.fit_forest`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import pytorch_lightning as pl
import torch
from hydra.utils import instantiate

from meshseg.data.mesh import Mesh
from meshseg.data.splits import Fold
from meshseg.errors import ConfigError
from meshseg.training.data import FeatureSource, TrainSet, build_train, iter_test_inputs
from meshseg.training.module import Segmenter
from meshseg.training.stages import Fitted, device_of, fit_autoencoder, fit_forest, train_stage

log = logging.getLogger(__name__)


@dataclass
class FoldPredictions:
    meshes: list[Mesh]  # the test meshes, in fold order
    probabilities: list[np.ndarray]  # per mesh (faces, classes) float32
    timings: dict[str, float] = field(default_factory=dict)  # seconds: features, train, predict
    counts: dict[str, int] = field(default_factory=dict)  # train samples, train/test faces
    parts: dict[str, object] = field(default_factory=dict)  # the fitted model's parts by stage name


def build_net(net_cfg, n_features: int, n_classes: int, branches: int) -> torch.nn.Module:
    """The configured network (`_target_` + its arguments) for this fold's input and label sizes."""
    return instantiate(net_cfg, n_features=n_features, n_classes=n_classes, branches=branches)


def fit_net(train: TrainSet, n_classes: int, model_cfg, budget, trainer_cfg, seed: int, logger=None) -> Fitted:
    """One network trained with cross-entropy by the paper's optimiser (Segmenter)."""
    net = build_net(model_cfg.net, train.X.shape[2], n_classes, train.X.shape[1])
    if hasattr(net, "fit_frozen"):
        net.fit_frozen(train.X)  # e.g. the PCA of pca_nn: from the training faces only
    module = Segmenter(net, budget.epochs, **model_cfg.optim)
    train_stage(module, train, budget, trainer_cfg, seed, logger)
    module.to(device_of(trainer_cfg))
    return Fitted({"net": net}, lambda X: module.predict_proba(X, trainer_cfg.predict_batch_size), budget.epochs)


FITTERS = {"net": fit_net, "autoencoder": fit_autoencoder, "forest": fit_forest}


def fit_predict(
    source: FeatureSource, fold: Fold, model_cfg, budget, trainer_cfg, seed: int, workers: int = 2, logger=None
) -> FoldPredictions:
    """Features (from the cache or computed), the model fitted on the fold's training meshes as the
    budget says, then class probabilities for every face of every test mesh."""
    kind = model_cfg.get("kind", "net")
    if kind not in FITTERS:
        raise ConfigError(f"model {model_cfg.name}: kind={kind!r} is not known: choose one of {sorted(FITTERS)}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    source.prepare([*fold.train, *fold.test], workers)
    train = build_train(source, fold.train, budget.faces_per_mesh, seed)
    timings["features"] = time.perf_counter() - t0
    n_classes = len(source.dataset.label_names(source.category))
    log.info(
        "fold %d: %d training faces sampled from %d (%d meshes), %d classes",
        fold.index,
        len(train.y),
        train.mesh_faces,
        len(fold.train),
        n_classes,
    )

    pl.seed_everything(seed, workers=True, verbose=False)
    t0 = time.perf_counter()
    fitted = FITTERS[kind](train, n_classes, model_cfg, budget, trainer_cfg, seed, logger)
    timings["train"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    meshes, probabilities = [], []
    for mesh, X in iter_test_inputs(source, fold.test, train.standardiser):
        meshes.append(mesh)
        probabilities.append(fitted.predict_proba(X))
    timings["predict"] = time.perf_counter() - t0
    counts = {
        "train_samples": len(train.y),
        "train_faces": train.mesh_faces,
        "test_faces": sum(m.n_faces for m in meshes),
        "epochs": fitted.epochs,
    }
    return FoldPredictions(meshes, probabilities, timings, counts, fitted.parts)
