"""A refinement's settings chosen per fold on meshes the model did not train on but that belong to the
fold's training meshes (e.g. the ones gbdt holds out for early stopping), never on a test mesh: the
refinement stage of a fold when `refine.search` is set (`fit_refinement`), as the fitter is the model's.

`refine.search` names a grid, e.g. `{lam: [0.5, 1, 2, 4], omega: [0, 1, 2, 4]}`; every combination is
tried in grid order (the settings by name, each one's values as listed) and the one with the highest mean
score over the held-out meshes wins (the first of equals, so the configured values win a tie when they are
the grid's first). The score is the caller's (the run passes the paper's accuracy): the refinement package
does not import the metrics.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence

import numpy as np

from meshseg.data.mesh import Mesh
from meshseg.refine.refinement import Refinement, candidates
from meshseg.timing import Timings
from meshseg.training.data import FeatureSource
from meshseg.training.fit import FoldPredictions

log = logging.getLogger(__name__)

#: the run artifact that holds a search's held-out meshes and every grid point's scores
SEARCH_RECORD = "refine_search.json"


@dataclasses.dataclass
class SearchResult:
    chosen: Refinement  # the refinement to apply to the test meshes
    settings: dict  # its grid point, e.g. {"lam": 1.0, "omega": 2.0}
    score: float  # its mean score over the held-out meshes
    table: list[dict]  # every grid point with its mean score and per-mesh scores, in grid order


def choose(
    refinement: Refinement,
    meshes: Sequence[Mesh],
    probabilities: Sequence[np.ndarray],
    features: Sequence[np.ndarray | None],
    score: Callable[[Mesh, np.ndarray], float],
) -> SearchResult:
    """The grid point of `refinement.search` whose refinement of the held-out `meshes` (their model
    probabilities and the refinement's features) scores highest on average."""
    if not meshes:
        raise ValueError("refine.search needs at least one held-out mesh to choose on")
    grid = candidates(refinement, refinement.search)
    log.info("refine.search: %d grid points on %d held-out meshes", len(grid), len(meshes))
    table, best = [], 0
    for i, (point, candidate) in enumerate(grid, 1):
        scores = [score(m, candidate(m, p, f)) for m, p, f in zip(meshes, probabilities, features, strict=True)]
        table.append({**point, "score": float(np.mean(scores)), "per_mesh": [float(s) for s in scores]})
        if table[-1]["score"] > table[best]["score"]:
            best = len(table) - 1
        log.info("refine.search %d/%d %s: %.4f (best %s)", i, len(grid), point, table[-1]["score"], grid[best][0])
    point, chosen = grid[best]
    return SearchResult(chosen, point, table[best]["score"], table)


@dataclasses.dataclass
class FittedRefinement:
    """A fold's refinement once fitted: the one to apply, and what the fitting leaves in the run."""

    refinement: Refinement
    settings: dict  # the grid point chosen ({}: the configured settings, nothing searched)
    metrics: dict[str, float]  # refine/<setting> and refine/held_out_acc
    records: dict[str, dict]  # run artifacts, by name (SEARCH_RECORD)


def fit_refinement(
    refinement: Refinement,
    preds: FoldPredictions,
    source: FeatureSource,
    score: Callable[[Mesh, np.ndarray], float],
    timings: Timings,
) -> FittedRefinement:
    """The fold's refinement: as configured, or with `refinement.search` the grid point that scores best (the
    caller's `score`, mean over the meshes) on the training meshes the fitter held out, refined from the
    probabilities of the model fitted without them (`preds.predict_held_out`). A model that held none out
    keeps the configured settings, with a warning. Timed as `predict_held_out` and `refine_search`."""
    if refinement.search is None:
        return FittedRefinement(refinement, {}, {}, {})
    meshes, probabilities = preds.predict_held_out(source, timings)
    if not meshes:  # one class in the training faces: nothing held out
        log.warning("refine.search: the model held no training mesh out; the configured settings stay")
        return FittedRefinement(refinement, {}, {}, {})
    with timings("refine_search"):
        features = [source.groups(m, refinement.needs) for m in meshes]
        found = choose(refinement, meshes, probabilities, features, score)
    log.info(
        "refine.search: %s chosen on %d held-out training meshes (%s): accuracy %.4f, best of %d grid points",
        found.settings,
        len(meshes),
        ", ".join(m.id for m in meshes),
        found.score,
        len(found.table),
    )
    metrics = {**{f"refine/{k}": float(v) for k, v in found.settings.items()}, "refine/held_out_acc": found.score}
    record = {"held_out": [m.id for m in meshes], "grid": found.table}
    return FittedRefinement(found.chosen, found.settings, metrics, {SEARCH_RECORD: record})
