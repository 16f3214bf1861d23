"""A refinement's settings chosen per fold on meshes the model did not train on but that belong to the
fold's training meshes (e.g. the ones gbdt holds out for early stopping), never on a test mesh.

`refine.search` names a grid, e.g. `{lam: [0.5, 1, 2, 4], omega: [0, 1, 2, 4]}`; every combination is
tried in grid order (the settings by name, each one's values as listed) and the one with the highest mean
score over the held-out meshes wins (the first of equals, so the configured values win a tie when they are
the grid's first). The score is the caller's (the run passes the paper's accuracy): the refinement package
does not import the metrics.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from meshseg.data.mesh import Mesh
from meshseg.errors import ConfigError
from meshseg.refine.refinement import Refinement


def numeric_settings(refinement: Refinement) -> list[str]:
    """The settings of `refinement` a grid may range over: its numbers (a chosen value is logged as a metric)."""
    if not dataclasses.is_dataclass(refinement):
        return []
    defaults = {f.name: f.default for f in dataclasses.fields(refinement)}
    return sorted(k for k, v in defaults.items() if isinstance(v, int | float) and not isinstance(v, bool))


def grid_points(refinement: Refinement, grid: dict) -> list[dict]:
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
    return [dict(zip(keys, combo)) for combo in itertools.product(*(list(grid[k]) for k in keys))]


def candidates(refinement: Refinement, grid: dict) -> list[tuple[dict, Refinement]]:
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
    table, best = [], 0
    for point, candidate in grid:
        scores = [score(m, candidate(m, p, f)) for m, p, f in zip(meshes, probabilities, features, strict=True)]
        table.append({**point, "score": float(np.mean(scores)), "per_mesh": [float(s) for s in scores]})
        if table[-1]["score"] > table[best]["score"]:
            best = len(table) - 1
    point, chosen = grid[best]
    return SearchResult(chosen, point, table[best]["score"], table)
