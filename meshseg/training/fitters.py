"""Fitters: how a model is trained on a fold's faces. Each is a class named by `_target_` in
`conf/model/*.yaml`, shaped like a scikit-learn estimator: its hyperparameters (the YAML's keys) and the
run's `TrainContext` go to the constructor, `fit(train)` trains on a `TrainSet` and returns the fitter,
`predict_proba(X)` gives (n, classes) float32 for standardised inputs (n, branches, features), and
`predict_mesh(mesh, X)` those of a whole mesh (the same, unless the fitter reads the surface too).

After `fit`, `parts_` holds the trained parts by stage name (net, ae1, forest, ...) and `epochs_` the
passes made over the training faces by all network stages. A new method is one such class (or, for a
network, one `nn.Module` under `NetFitter`) and one YAML file: see docs/adding-a-method.md.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import nn

from meshseg.errors import ConfigError
from meshseg.models.forest import RandomForest
from meshseg.models.gbdt import GradientBoostedTrees
from meshseg.models.settings import ForestSettings, GbdtSettings
from meshseg.training.context import TrainContext

if TYPE_CHECKING:
    from meshseg.training.data import TrainSet

log = logging.getLogger("meshseg.training")


class Fitter:
    """Base of every fitter: keeps the run's context; subclasses implement `fit` and `predict_proba`."""

    #: whether it trains epoch by epoch (budget.resample=epoch means something only then)
    epochs_trained = True
    #: whether `fit` holds whole training meshes out (`held_out_`, their ids), predictable with the model
    #: fitted without them (`predict_held_out`): what refine.search chooses on
    holds_out_meshes = False

    def __init__(self, context: TrainContext):
        if context.resample == "epoch" and not self.epochs_trained:
            raise ConfigError(
                f"budget.resample=epoch is not allowed with {type(self).__name__}: it fits once on a fold's "
                "sampled faces, not epoch by epoch (use budget.resample=fold)"
            )
        self.context = context
        self.parts_: dict[str, object] = {}
        self.epochs_ = 0

    def check_fold(self, n_train_meshes: int) -> None:
        """Refuse a setting the fold's training meshes cannot satisfy (a ConfigError), before any feature is
        computed; most fitters take any number."""

    def fit(self, train: TrainSet) -> Fitter:
        raise NotImplementedError

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def predict_mesh(self, mesh, X: np.ndarray) -> np.ndarray:
        """Probabilities of every face of `mesh` (a meshseg Mesh), X its standardised inputs: what a run and a
        logged model call. Most fitters need X alone; one that reads the surface (model=stacked) overrides it."""
        return self.predict_proba(X)

    def predict_held_out(self, X: np.ndarray) -> np.ndarray:
        raise NotImplementedError(f"{type(self).__name__} holds no training meshes out")

    def fitted(self) -> dict[str, float]:
        """What `fit` chose, logged as the run's metrics (none for most fitters)."""
        return {}

    def __getstate__(self) -> dict:
        # a fitter saved with its run (the model/ artifact) keeps its trained parts, not the run's logger
        state = dict(self.__dict__)
        state["context"] = dataclasses.replace(self.context, logger=None, checkpoint_dir=None)
        return state

    def to_cpu(self) -> Fitter:
        """Its networks and context moved to the CPU (a model trained on a GPU, used where there is none)."""
        self.context = dataclasses.replace(self.context, accelerator="cpu", devices=1, logger=None)
        for part in self.__dict__.values():
            if isinstance(part, nn.Module):
                part.to(torch.device("cpu"))
        return self


class NetFitter(Fitter):
    """One network trained with cross-entropy by the paper's optimiser (`Segmenter`, §3.4): cnn1d,
    cnn2d, pca_nn. `net` builds the network for the fold's sizes (the YAML's `net:` node, a partial:
    `net(n_features=, n_classes=, branches=)`); a network with frozen data-fitted layers (pca_nn's PCA)
    has them fitted first, on the training faces only, by its `fit_frozen`.

    A network class with a `Settings` attribute (a meshseg.models.settings class) has the partial's
    settings checked here, when the method is built: before any feature is computed."""

    def __init__(self, net: Callable[..., nn.Module], optim: dict, context: TrainContext):
        super().__init__(context)
        settings = getattr(getattr(net, "func", None), "Settings", None)
        if settings is not None:
            settings.of(net.keywords)
        self.net, self.optim = net, dict(optim)

    def fit(self, train: TrainSet) -> NetFitter:
        # Lightning is imported to train, not to build: a bad setting is refused before that import (seconds)
        from meshseg.training.loop import train_stage
        from meshseg.training.module import Segmenter

        ctx = self.context
        net = self.net(n_features=train.X.shape[2], n_classes=train.n_classes, branches=train.X.shape[1])
        if hasattr(net, "fit_frozen"):
            net.fit_frozen(train.X)
        self.module_ = Segmenter(net, ctx.epochs, **self.optim)
        train_stage(self.module_, train, ctx)
        self.module_.to(ctx.device)
        self.parts_, self.epochs_ = {"net": net}, ctx.epochs
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        return self.module_.predict_proba(X, self.context.predict_batch_size)


def make_forest(forest: dict, n_classes: int, ctx: TrainContext) -> RandomForest:
    """The configured forest; its worker count is the trainer's thread count (all cores when null)."""
    return RandomForest(n_classes, **forest, n_jobs=ctx.threads or -1, seed=ctx.seed)


class ForestFitter(Fitter):
    """A random forest on the (standardised, single-scale) features of the training faces (rf: the
    paper's CF figure). `forest`: scikit-learn RandomForestClassifier settings."""

    epochs_trained = False

    def __init__(self, forest: dict, context: TrainContext):
        super().__init__(context)
        self.forest = dict(forest)
        ForestSettings.of(self.forest)  # checked when the method is built

    def fit(self, train: TrainSet) -> ForestFitter:
        self.forest_ = make_forest(self.forest, train.n_classes, self.context).fit(train.X, train.y)
        self.parts_, self.epochs_ = {"forest": self.forest_}, 1
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        return self.forest_.predict_proba(X)


class GbdtFitter(Fitter):
    """Gradient-boosted trees (gbdt, not in the paper) on the standardised features of the training faces,
    X^1..X^B concatenated. `trees`: GbdtSettings. Early stopping holds out whole training meshes; after `fit`,
    `held_out_` names them and `rounds_` is the number of boosting rounds kept."""

    epochs_trained = False
    holds_out_meshes = True

    def __init__(self, trees: dict, context: TrainContext):
        super().__init__(context)
        self.trees = dict(trees)
        GbdtSettings.of(self.trees)  # checked when the method is built

    def fit(self, train: TrainSet) -> GbdtFitter:
        ctx = self.context
        self.trees_ = GradientBoostedTrees(train.n_classes, n_jobs=ctx.threads or -1, seed=ctx.seed, **self.trees)
        self.trees_.fit(train.X, train.y, train.mesh_index)
        self.held_out_ = tuple(train.mesh_ids[i] for i in self.trees_.inner_)
        self.rounds_ = self.trees_.rounds_
        log.info("gbdt: %d rounds, chosen on held-out training meshes %s", self.rounds_, ", ".join(self.held_out_))
        self.parts_, self.epochs_ = {"trees": self.trees_}, 1
        return self

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        return self.trees_.predict_proba(X)

    def predict_held_out(self, X: np.ndarray) -> np.ndarray:
        return self.trees_.predict_proba(X, held_out=True)

    def fitted(self) -> dict[str, float]:
        return {"gbdt/rounds": float(self.rounds_)}  # the held-out meshes: the log, and refine.search's record


def build_fitter(model_cfg, context: TrainContext) -> Fitter:
    """The fitter a `conf/model/*.yaml` node names, with the run's context."""
    from meshseg.instantiate import build

    fitter = build(model_cfg, f"model={model_cfg.get('name', '?')}", context=context)
    if not isinstance(fitter, Fitter):
        raise ConfigError(
            f"model={model_cfg.get('name', '?')}: {model_cfg._target_} is not a meshseg.training.fitters.Fitter"
        )
    return fitter
