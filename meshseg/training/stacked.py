"""A stacked second stage that sees the labels around each face (model=stacked; not in the paper:
docs/deviations.md G3). A per-face classifier cannot see the rest of the shape, and labels whole parts as
another part of like local shape (a cup's body as its handle); Kalogerakis et al. 2010 answer with a second
boosting stage on contextual label features. Here:

1. Stage 1, any meshseg model (`stage1`: a conf/model node; GBDT by default), fitted `inner_folds` times, each
   time without one group of the training meshes, and predicting every face of that group: out-of-fold
   probabilities for every training mesh, from a model that never saw it. The test mesh is never a training
   mesh, so it is in no inner fold.
2. Context features of those probabilities on each training mesh (meshseg/features/label_context.py).
3. Stage 2, gradient-boosted trees (`stage2`: GbdtSettings) on [the face's own inputs, its context
   features], on the training faces the budget sampled.

A test mesh (`test_stage1`): with `each`, every inner stage-1 model labels it, stage 2 reads the context of each
labelling, and stage 2's k probabilities are averaged, so stage 2 sees what it was trained on: the context of one
model fitted on (k-1)/k of the training meshes. With `mean`, stage 2 reads the context of the inner models' mean
probabilities once, a smoother labelling than any training mesh's. Neither refits stage 1 on all the training
meshes. The run's refinement follows as for every model.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from meshseg.errors import ConfigError
from meshseg.features.label_context import LabelContext, MeshContext
from meshseg.models.gbdt import GradientBoostedTrees
from meshseg.models.settings import GbdtSettings
from meshseg.training.context import TrainContext
from meshseg.training.data import TrainSet, iter_test_inputs
from meshseg.training.fitters import Fitter, build_fitter

log = logging.getLogger("meshseg.training")


def inner_groups(n_meshes: int, folds: int, seed: int) -> list[np.ndarray]:
    """The training meshes (positions 0..n-1) in `folds` groups of near-equal size, shuffled by a generator
    seeded with `seed`; each group sorted."""
    if not 2 <= folds <= n_meshes:
        raise ConfigError(
            f"model.inner_folds={folds}: needs 2 <= inner_folds <= the fold's training meshes ({n_meshes})"
        )
    order = np.random.default_rng([seed, 53]).permutation(n_meshes)
    return [np.sort(g) for g in np.array_split(order, folds)]


class StackedFitter(Fitter):
    """Stage 1 out of fold, context features, stage 2 (see the module doc). After `fit`: `inner_` the inner
    stage-1 fitters, `inner_meshes_` per inner fold (ids trained on, ids predicted), `trees_` stage 2,
    `seconds_` the time of each part."""

    epochs_trained = False  # stage 2 fits once; rows drawn per epoch cannot be split by mesh

    #: how a test mesh reaches stage 2: see the module doc
    TEST_STAGE1 = ("each", "mean")

    def __init__(
        self,
        stage1,
        inner_folds: int,
        context_features: dict,
        stage2: dict,
        context: TrainContext,
        test_stage1: str = "each",
    ):
        super().__init__(context)
        if test_stage1 not in self.TEST_STAGE1:
            raise ConfigError(f"model.test_stage1={test_stage1}: one of {list(self.TEST_STAGE1)}")
        self.test_stage1 = test_stage1
        if getattr(stage1, "name", None) == "stacked":
            raise ConfigError("model.stage1: stage 1 must be a per-face model, not another stack")
        self.stage1 = stage1
        build_fitter(stage1, context)  # a bad stage-1 setting is refused now, before any feature is computed
        self.inner_folds = int(inner_folds)
        if self.inner_folds < 2:
            raise ConfigError(f"model.inner_folds={inner_folds}: at least 2 (stage 1 out of fold)")
        self.features = LabelContext.of(dict(context_features))
        self.stage2 = dict(stage2)
        GbdtSettings.of(self.stage2)

    def check_fold(self, n_train_meshes: int) -> None:
        inner_groups(n_train_meshes, self.inner_folds, seed=0)  # its ConfigError names the fold's meshes

    def fit(self, train: TrainSet) -> StackedFitter:
        if train.source is None or train.faces is None:
            raise ValueError("model=stacked needs the training set's source and face indices (build_train gives them)")
        ctx, n_classes = self.context, train.n_classes
        inner_ctx = dataclasses.replace(ctx, logger=None, checkpoint_dir=None)
        self.inner_, self.inner_meshes_, oof = [], [], {}
        t0 = time.perf_counter()
        for k, held in enumerate(inner_groups(len(train.mesh_ids), self.inner_folds, ctx.seed)):
            kept = [i for i in range(len(train.mesh_ids)) if i not in set(held.tolist())]
            part = train.of_meshes(kept)
            fitter = build_fitter(self.stage1, inner_ctx).fit(part)
            predicted = [train.mesh_ids[i] for i in held]
            for mesh_id, (mesh, X) in zip(predicted, iter_test_inputs(train.source, predicted, train.standardiser)):
                oof[mesh_id] = fitter.predict_mesh(mesh, X)
            self.inner_.append(fitter)
            self.inner_meshes_.append((part.mesh_ids, tuple(predicted)))
            log.info(
                "stacked: stage 1, inner fold %d of %d predicted %s", k + 1, self.inner_folds, ", ".join(predicted)
            )
        t1 = time.perf_counter()
        context = np.empty((len(train.y), len(self.features.names(n_classes))), dtype=np.float32)
        for i, mesh_id in enumerate(train.mesh_ids):
            mesh, rows = train.source.mesh(mesh_id), np.flatnonzero(train.mesh_index == i)
            every_face = MeshContext(mesh.vertices, mesh.faces, self.features).features(oof[mesh_id])
            context[rows] = every_face[train.faces[rows]]
        t2 = time.perf_counter()
        self.trees_ = GradientBoostedTrees(n_classes, n_jobs=ctx.threads or -1, seed=ctx.seed, **self.stage2)
        self.trees_.fit(self._inputs(train.X, context), train.y, train.mesh_index)
        self.seconds_ = {"stage1": t1 - t0, "context": t2 - t1, "stage2": time.perf_counter() - t2}
        times = ", ".join(f"{k} {v:.1f} s" for k, v in self.seconds_.items())
        log.info("stacked: stage 2, %d rounds; %s", self.trees_.rounds_, times)
        self.parts_ = {**{f"stage1_{k}": f for k, f in enumerate(self.inner_)}, "trees": self.trees_}
        self.epochs_ = 1
        return self

    @staticmethod
    def _inputs(X: np.ndarray, context: np.ndarray) -> np.ndarray:
        return np.concatenate([X.reshape(len(X), -1), context], axis=1)

    def stage1_proba(self, mesh, X: np.ndarray) -> list[np.ndarray]:
        """Stage 1's labellings of a mesh that none of its inner models trained on: one per inner model
        (`test_stage1=each`), or their mean alone (`mean`)."""
        each = [f.predict_mesh(mesh, X) for f in self.inner_]
        return each if self.test_stage1 == "each" else [np.mean(each, axis=0)]

    def predict_mesh(self, mesh, X: np.ndarray) -> np.ndarray:
        surface = MeshContext(mesh.vertices, mesh.faces, self.features)  # one setup for every labelling
        stage2 = [self.trees_.predict_proba(self._inputs(X, surface.features(P))) for P in self.stage1_proba(mesh, X)]
        return np.mean(stage2, axis=0)

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        raise TypeError("model=stacked reads the surface around each face: predict whole meshes (predict_mesh)")

    def fitted(self) -> dict[str, float]:
        return {
            "stacked/inner_folds": float(self.inner_folds),
            "stacked/stage2_rounds": float(self.trees_.rounds_),
            **{f"stacked/{k}_s": v for k, v in self.seconds_.items()},
        }

    def to_cpu(self) -> StackedFitter:
        super().to_cpu()
        for f in self.inner_:
            f.to_cpu()
        return self
