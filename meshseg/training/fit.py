"""Train one fold and predict every face of its test meshes: features (cached), the training faces
sampled and standardised as the budget says, the model's fitter (`conf/model/*.yaml`, `_target_`, built
by `build_fitter`) fitted on them, then class probabilities for every test face."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
import pytorch_lightning as pl

from meshseg.data.mesh import Mesh
from meshseg.timing import Timings
from meshseg.training.data import FeatureSource, build_train, iter_test_inputs
from meshseg.training.fitters import Fitter

log = logging.getLogger(__name__)


@dataclass
class FoldPredictions:
    meshes: list[Mesh]  # the test meshes, in fold order
    probabilities: list[np.ndarray]  # per mesh (faces, classes) float32
    timings: dict[str, float] = field(default_factory=dict)  # seconds per phase (see fit_predict)
    counts: dict[str, int] = field(default_factory=dict)  # train samples, train/test faces, epochs
    parts: dict[str, object] = field(default_factory=dict)  # the fitted model's parts by stage name
    fitter: object | None = None  # the fitted fitter and the standardiser of its inputs: the fold's model
    standardiser: object | None = None

    def predict_held_out(self, source: FeatureSource, timings: Timings) -> tuple[list[Mesh], list[np.ndarray]]:
        """The training meshes the fitter held out (`held_out_`: gbdt's early-stopping meshes; none for the
        others) and, for every face, the probabilities of the model it fitted without them: what a refinement
        may choose its settings on (meshseg.refine.search). Timed as `predict_held_out` (read and predicted)."""
        if not getattr(self.fitter, "holds_out_meshes", False):
            return [], []
        aside = replace(source, timings=Timings())  # their reads stay out of the test meshes' phases
        with timings("predict_held_out"):
            held = [
                (m, self.fitter.predict_held_out(X))
                for m, X in iter_test_inputs(aside, self.fitter.held_out_, self.standardiser)
            ]
        return [m for m, _ in held], [p for _, p in held]


def fit_predict(source: FeatureSource, fitter: Fitter, faces_per_mesh: int | None, workers: int = 2) -> FoldPredictions:
    """Features (from the cache or computed), the fitter (built by `build_fitter`, with the run's context)
    fitted on the training meshes of the source's fold (`faces_per_mesh` sampled from each, all when None),
    then class probabilities for every face of every test mesh.

    Timings (seconds): `features` (computing what the cache lacks), `mesh` (reading meshes), `load`
    (reading cached features), `rings` (X^1..X^B), `standardise`, `train`, `predict` (the model only)."""
    ctx, fold = fitter.context, source.fold
    timings = source.timings
    with timings("features"):
        source.prepare([*fold.train, *fold.test], workers)
    epochs = ctx.epochs if ctx.resample == "epoch" else None
    train = build_train(source, fold.train, faces_per_mesh, ctx.seed, epochs)
    log.info(
        "fold %d: %d training faces sampled from %d (%d meshes), %d classes%s",
        fold.index,
        len(train.y),
        train.mesh_faces,
        len(fold.train),
        train.n_classes,
        f"; {train.samples_per_epoch} of them each epoch" if train.epoch_rows is not None else "",
    )

    pl.seed_everything(ctx.seed, workers=True, verbose=False)
    with timings("train"):
        fitter.fit(train)

    log.info("fold %d: trained in %.1f s; predicting %d test meshes", fold.index, timings["train"], len(fold.test))
    meshes, probabilities = [], []
    for mesh, X in iter_test_inputs(source, fold.test, train.standardiser):
        meshes.append(mesh)
        with timings("predict"):
            probabilities.append(fitter.predict_mesh(mesh, X))
    counts = {
        "train_samples": train.samples_per_epoch,
        "train_distinct": len(train.y),  # faces any epoch trained on (more than train_samples with resample=epoch)
        "train_faces": train.mesh_faces,
        "test_faces": sum(m.n_faces for m in meshes),
        "epochs": fitter.epochs_,
    }
    return FoldPredictions(
        meshes,
        probabilities,
        dict(timings),
        counts,
        fitter.parts_,
        fitter,
        train.standardiser,
    )
