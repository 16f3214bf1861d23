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
import itertools
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np

from meshseg.errors import ConfigError

if TYPE_CHECKING:  # annotations only: the refine package needs no torch
    from meshseg.data.mesh import Mesh
    from meshseg.timing import Timings
    from meshseg.training.data import FeatureSource
    from meshseg.training.fit import FoldPredictions

log = logging.getLogger(__name__)


class Searchable(Protocol):
    """What a search needs of a refinement (meshseg.refine.Refinement, which imports this module): a dataclass
    whose fields are its settings, called on a mesh's probabilities and the feature groups it `needs`."""

    name: str
    needs: tuple[str, ...]
    search: dict | None

    def __call__(self, mesh: Mesh, probabilities: np.ndarray, features: np.ndarray | None = None) -> np.ndarray: ...


#: the run artifact that holds a search's held-out meshes and every grid point's scores
SEARCH_RECORD = "refine_search.json"


# The grid `refine.search` ranges over, checked when the refinement is built (build_refinement), then chosen from
# per fold (choose).
def numeric_settings(refinement: Searchable) -> list[str]:
    """The settings of `refinement` a grid may range over: its numbers (a chosen value is logged as a metric)."""
    if not dataclasses.is_dataclass(refinement):
        return []
    defaults = {f.name: f.default for f in dataclasses.fields(refinement)}
    return sorted(k for k, v in defaults.items() if isinstance(v, int | float) and not isinstance(v, bool))


#: the most points a refine.search grid may have: each costs a graph cut of every held-out mesh (seconds each)
MAX_GRID_POINTS = 100


def grid_points(refinement: Searchable, grid: dict) -> list[dict]:
    """Every combination of the grid's values, as settings of `refinement`, in grid order (settings sorted by
    name, values as listed); a grid that is not settings with non-empty lists of numbers, or a key that is
    not a numeric setting, is refused."""
    if not isinstance(grid, Mapping) or not grid:
        raise ConfigError(
            f"refine.search={grid} is not allowed: give settings with lists of values, e.g. {{lam: [1, 2]}}"
        )
    allowed = numeric_settings(refinement)
    for key, values in grid.items():
        if key not in allowed:
            raise ConfigError(
                f"refine.search.{key} is not allowed with refine={refinement.name}: it takes "
                f"{', '.join(allowed) or 'no settings'}"
            )
        numbers = isinstance(values, Sequence) and not isinstance(values, str) and len(values) > 0
        if not numbers or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
            raise ConfigError(f"refine.search.{key}={values} is not allowed: it must be a non-empty list of numbers")
    keys = sorted(grid)  # the config hash sorts the keys too: one hash, one order, one tie-break
    size = math.prod(len(grid[k]) for k in keys)
    if size > MAX_GRID_POINTS:  # counted before any point is built: 10^6 points were 1.3 GB and days of cuts
        shape = " x ".join(f"{len(grid[k])} {k}" for k in keys)
        raise ConfigError(
            f"refine.search has {size:,} points ({shape}): at most {MAX_GRID_POINTS} are allowed, "
            "each one a graph cut of every held-out mesh of every fold"
        )
    return [dict(zip(keys, combo)) for combo in itertools.product(*(list(grid[k]) for k in keys))]


def candidates(refinement: Searchable, grid: dict) -> list[tuple[dict, Searchable]]:
    """Each grid point with the refinement at it (checked as if configured so), with no search of its own."""
    out = []
    for point in grid_points(refinement, grid):
        try:
            out.append((point, dataclasses.replace(refinement, search=None, **point)))
        except ConfigError as e:  # the grid's value, not the configured one, is what is wrong
            raise ConfigError(f"refine.search {point}: {e}") from None
    return out


@dataclasses.dataclass
class SearchResult:
    chosen: Searchable  # the refinement to apply to the test meshes
    settings: dict  # its grid point, e.g. {"lam": 1.0, "omega": 2.0}
    score: float  # its mean score over the held-out meshes
    table: list[dict]  # every grid point with its mean score and per-mesh scores, in grid order


def choose(
    refinement: Searchable,
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

    refinement: Searchable
    settings: dict  # the grid point chosen ({}: the configured settings, nothing searched)
    metrics: dict[str, float]  # refine/<setting> and refine/held_out_acc
    records: dict[str, dict]  # run artifacts, by name (SEARCH_RECORD)


def fit_refinement(
    refinement: Searchable,
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
