"""Train one fold and predict every face of its test meshes."""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import pytorch_lightning as pl
import torch
from hydra.utils import instantiate

from meshseg.data.mesh import Mesh
from meshseg.data.splits import Fold
from meshseg.training.data import FeatureSource, FoldDataModule, build_train, iter_test_inputs
from meshseg.training.module import Segmenter

log = logging.getLogger(__name__)


@dataclass
class FoldPredictions:
    meshes: list[Mesh]                 # the test meshes, in fold order
    probabilities: list[np.ndarray]    # per mesh (faces, classes) float32
    timings: dict[str, float] = field(default_factory=dict)   # seconds: features, train, predict
    counts: dict[str, int] = field(default_factory=dict)      # train samples, train/test faces


def build_net(net_cfg, n_features: int, n_classes: int, branches: int) -> torch.nn.Module:
    """The configured network (`_target_` + its arguments) for this fold's input and label sizes."""
    return instantiate(net_cfg, n_features=n_features, n_classes=n_classes, branches=branches)


def fit_predict(source: FeatureSource, fold: Fold, model_cfg, budget, trainer_cfg, seed: int,
                workers: int = 2, logger=None) -> FoldPredictions:
    """Features (from the cache or computed), the network trained on the fold's training meshes as
    the budget says, then class probabilities for every face of every test mesh."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    source.prepare([*fold.train, *fold.test], workers)
    train = build_train(source, fold.train, budget.faces_per_mesh, seed)
    timings["features"] = time.perf_counter() - t0
    n_classes = len(source.dataset.label_names(source.category))
    log.info("fold %d: %d training faces sampled from %d (%d meshes), %d classes",
             fold.index, len(train.y), train.mesh_faces, len(fold.train), n_classes)

    pl.seed_everything(seed, workers=True, verbose=False)
    net = build_net(model_cfg.net, train.X.shape[2], n_classes, train.X.shape[1])
    module = Segmenter(net, budget.epochs, **model_cfg.optim)
    trainer = pl.Trainer(max_epochs=budget.epochs, accelerator=trainer_cfg.accelerator, devices=trainer_cfg.devices,
                         precision=trainer_cfg.precision, logger=logger or False, enable_checkpointing=False,
                         enable_progress_bar=trainer_cfg.progress_bar, enable_model_summary=False,
                         num_sanity_val_steps=0, log_every_n_steps=1)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        # One in-memory tensor dataset: DataLoader worker processes would only add copies.
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        warnings.filterwarnings("ignore", message=".*LeafSpec.*is deprecated")  # Lightning 2.6 on torch 2.13
        trainer.fit(module, datamodule=FoldDataModule(train, budget.batch_size, seed))
    timings["train"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    device = torch.device("cuda") if trainer_cfg.accelerator == "gpu" else torch.device("cpu")
    module.to(device)
    meshes, probabilities = [], []
    for mesh, X in iter_test_inputs(source, fold.test, train.standardiser):
        meshes.append(mesh)
        probabilities.append(module.predict_proba(X, trainer_cfg.predict_batch_size))
    timings["predict"] = time.perf_counter() - t0
    counts = {"train_samples": len(train.y), "train_faces": train.mesh_faces,
              "test_faces": sum(m.n_faces for m in meshes), "epochs": budget.epochs}
    return FoldPredictions(meshes, probabilities, timings, counts)
