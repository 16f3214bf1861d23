"""Refine what a store's fold runs predicted again, at other values of one refinement setting, without training.

    python scripts/rerefine.py dataset=psb split=loo model=ae_rf category=Fish lam=[0.25,0.5,1,2,4]
    python scripts/rerefine.py tracking.uri=sqlite:///elsewhere/mlflow.db dataset=psb split=5fold model=cnn1d \
        branches=3 category=Vase omega=[0,1,2,4]

The runs are the folds of one category under the run overrides given, composed as `meshseg.run` composes them
(their config hashes find them in the store, `tracking.uri`). Each FINISHED fold run logged its test meshes'
per-face probabilities (`predictions.npz`); they are refined again with the run's own refinement at each value of
the setting (one of the refinement's numeric settings: lam, omega, eps, ...), and one markdown row per test mesh
prints the argmax accuracy, the logged accuracy and the accuracy at each value, then their means. The logged
value of the setting replays the logged labels exactly; that is checked, and a mismatch is an error.

A diagnostic, not a run: nothing is logged or chosen. Settings picked this way would be picked on test meshes,
a selection effect; `refine.search` chooses on held-out training meshes instead (docs/methods.md).
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from meshseg.errors import ConfigError, MeshsegError, TrackingError  # noqa: E402


def rerefine(mesh, probabilities, features, refinement, setting: str, values) -> list[float]:
    """Area-weighted accuracy (%) of `refinement` at each value of `setting` on one mesh's probabilities."""
    from meshseg.metrics import area_weighted_accuracy

    return [
        100
        * area_weighted_accuracy(
            dataclasses.replace(refinement, **{setting: v})(mesh, probabilities, features), mesh.labels, mesh.face_areas
        )
        for v in values
    ]


def split_argv(argv: list[str]) -> tuple[str, list[float], list[str]]:
    """(setting, values, run overrides) from the command line: the one `<setting>=[v,...]` whose key has no dot
    and names no run-config key, and the rest."""
    grid = [a for a in argv if "=" in a and "." not in a.split("=", 1)[0] and a.split("=", 1)[1].startswith("[")]
    grid = [a for a in grid if a.split("=", 1)[0] not in ("category", "fold")]
    if len(grid) != 1:
        raise ConfigError(f"give one refinement setting with its values, e.g. lam=[0.5,1,2]; got {grid or 'none'}")
    key, text = grid[0].split("=", 1)
    try:
        values = [float(v) for v in text.strip("[]").split(",")]
    except ValueError:
        raise ConfigError(f"{grid[0]}: the values must be numbers") from None
    return key, values, [a for a in argv if a != grid[0]]


def main(argv: list[str]) -> None:
    from mlflow import MlflowClient
    from omegaconf import OmegaConf

    from meshseg.config import run_config
    from meshseg.data.splits import build_split
    from meshseg.job import FoldJob
    from meshseg.metrics import area_weighted_accuracy
    from meshseg.refine.search import numeric_settings
    from meshseg.report.runs import finished_by_hash
    from meshseg.tracking import FoldRecord, check_store_exists, store_uri
    from meshseg.training.data import mesh_groups

    setting, values, overrides = split_argv(argv)
    cfg = run_config(overrides)
    first = FoldJob.from_config(cfg)
    if setting not in numeric_settings(first.refinement):
        raise ConfigError(
            f"{setting} is not a numeric setting of refine={first.refinement.name}: "
            f"choose one of {numeric_settings(first.refinement)}"
        )
    check_store_exists(cfg.tracking.uri)  # a store that is not there is not created
    runs, client = (
        finished_by_hash(cfg.tracking.uri, cfg.tracking.experiment),
        MlflowClient(store_uri(cfg.tracking.uri)),
    )
    logged_value = getattr(first.refinement, setting)
    n_folds = len(build_split(OmegaConf.create(first.config["split"])).folds(first.dataset, first.key.category))
    print("| mesh | fold | argmax | logged | " + " | ".join(f"{setting}={v:g}" for v in values) + " |")
    print("|---|---|---|---|" + "---|" * len(values))
    rows, missing = [], []
    for i in range(n_folds):
        cfg_i = OmegaConf.merge(cfg, {"fold": i})
        job = first if i == first.fold.index else FoldJob.from_config(cfg_i)
        run = runs.get(job.key.config_hash)
        if run is None:
            missing.append(i)
            continue
        with tempfile.TemporaryDirectory() as tmp:
            with np.load(client.download_artifacts(run.info.run_id, FoldRecord.PREDICTIONS, tmp)) as z:
                arrays = {k: z[k] for k in z.files}
        for mesh_id in job.fold.test:
            mesh = job.dataset.load(job.key.category, mesh_id)
            P = arrays[f"probs_{mesh_id}"].astype(np.float64)
            features = mesh_groups(mesh, job.features, job.refinement.needs, job.cache_dir)
            logged = 100 * area_weighted_accuracy(arrays[f"labels_{mesh_id}"], mesh.labels, mesh.face_areas)
            grid = list(dict.fromkeys([logged_value, *values]))  # the logged value is refined once, not twice
            acc = dict(zip(grid, rerefine(mesh, P, features, job.refinement, setting, grid)))
            replay = acc[logged_value]
            if abs(replay - logged) > 1e-6:
                raise TrackingError(
                    f"mesh {mesh_id} (fold {i}): refining the logged probabilities at {setting}={logged_value:g} "
                    f"gives {replay:.4f} %, the run logged {logged:.4f} % (did refine.search choose its settings?)"
                )
            row = [
                100 * area_weighted_accuracy(P.argmax(axis=1), mesh.labels, mesh.face_areas),
                logged,
                *(acc[v] for v in values),
            ]
            rows.append(row)
            print(f"| {mesh_id} | {i} | " + " | ".join(f"{x:.2f}" for x in row) + " |", flush=True)
    if not rows:
        raise ConfigError(f"no FINISHED fold run of these overrides in {cfg.tracking.uri}")
    mean = np.mean(rows, axis=0)
    print(f"| **mean** ({len(rows)} meshes) | | " + " | ".join(f"**{x:.2f}**" for x in mean) + " |")
    if missing:
        print(f"folds without a FINISHED run in the store (left out): {missing}")


if __name__ == "__main__":
    try:
        main(sys.argv[1:])
    except MeshsegError as e:  # bad input or a store without these runs: one line, no traceback
        sys.exit(f"error: {e}")
