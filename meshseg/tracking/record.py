"""What one fold's run records, defined once: `meshseg.run` writes it; the report, `reproduce`,
`meshseg.results` and the notebooks read it by these names."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from meshseg.tracking.identity import flatten
from meshseg.tracking.provenance import git_sha, machine, slurm_job, versions

#: the tag of a sweep's parent run (meshseg.tracking.sweeps), its value the sweep's identity: a run that is no fold,
#: which every search for fold runs leaves out
SWEEP_KEY = "sweep_key"


def is_fold_run(run) -> bool:
    """Whether a stored run is a fold's (or a report's), not a sweep's parent."""
    return SWEEP_KEY not in run.data.tags


@dataclass(frozen=True)
class RunKey:
    """What tells one fold's run from another's: the tags the report selects runs by (FoldRecord.TAGS, but
    the git commit) and, from them, the run's name."""

    dataset: str
    category: str
    model: str
    branches: int
    features: str
    split: str
    fold: int
    refine: str
    budget: str
    config_hash: str
    data_hash: str
    seed: int = 0  # the training seed (issue 51 runs folds at several)

    @classmethod
    def from_tags(cls, tags: Mapping) -> RunKey:
        """The key of a stored run or record, from its tags (strings)."""
        values = {f.name: tags[f.name] for f in dataclasses.fields(cls)}
        return cls(**{**values, **{k: int(values[k]) for k in ("branches", "fold", "seed")}})

    @property
    def name(self) -> str:
        """The run's name, what differs between a sweep's runs first (the UI's table cuts names short):
        `Glasses f2 · cnn1d 3B f800 · 5fold · cpu`, and `· seed 1` where the training seed is not 0 (so that a
        fold's runs at several seeds differ in name as in identity)."""
        k = self
        seed = f" · seed {k.seed}" if k.seed else ""
        return f"{k.category} f{k.fold} · {k.model} {k.branches}B {k.features} · {k.split} · {k.budget}{seed}"


class FoldRecord:
    """The record schema: tags, params, metrics, artifacts and their names."""

    #: tags every fold run carries (the report selects runs by these)
    TAGS = (
        "dataset",
        "category",
        "model",
        "branches",
        "features",
        "split",
        "fold",
        "refine",
        "budget",
        "config_hash",
        "git_sha",
        "data_hash",
        "seed",
    )
    #: the two accuracies every fold logs (area-weighted mean over the test meshes), after and before refinement.
    #: Metrics are named by role: train/* (per epoch, from Lightning), test/*, time/<phase>_s, speed/*,
    #: refine/* (what refine.search chose); counts (samples, faces, epochs) are params n_*.
    ACC, ACC_RAW = "test/acc", "test/acc_raw"
    #: artifact: the resolved config (YAML)
    CONFIG = "config.yaml"
    #: artifact: one row per test mesh, these columns (accuracies in [0, 1], area-weighted)
    PER_MESH = "per_mesh.csv"
    PER_MESH_COLUMNS = ("mesh", "faces", "area", "acc_raw", "acc")
    #: the per-mesh columns a report may average
    MESH_METRICS = ("acc", "acc_raw")
    #: artifact (runs with refine.search): the held-out meshes and every grid point's scores (JSON); the name
    #: meshseg.refine.search.SEARCH_RECORD gives it (a test keeps the two equal; the record needs no refine package)
    REFINE_SEARCH = "refine_search.json"
    #: artifact: per-face arrays, keys `<prefix><mesh id>` with these dtypes (and `classes`, the class count, where
    #: no `probs_` array gives it: a run imported from a record's labels)
    PREDICTIONS = "predictions.npz"
    PREDICTION_ARRAYS = {"labels_": "int16", "labels_raw_": "int16", "probs_": "float16", "classes": "int16"}
    #: the fold's model: the run's MLflow logged model of this name (`runs:/<run id>/model`, meshseg.pyfunc); runs
    #: made before logged models kept the same files as their `model/` artifact
    MODEL = "model"

    @staticmethod
    def tags(key: RunKey, fold, *, accelerator: str, overrides=None) -> dict:
        """The run's tags: TAGS (what the report selects by, the training seed among them), the accelerator, and
        provenance: the fold's mesh ids (`fold`: a `meshseg.data.splits.Fold`) and the Hydra overrides the run was
        launched with (so that `meshseg.results` can check a shipped record against the code), the machine, the
        package versions, and the SLURM job when one runs it (so a stuck run can be found and `scancel`led)."""
        k = key
        job = slurm_job()
        return {
            "dataset": k.dataset,
            "category": k.category,
            "model": k.model,
            "branches": k.branches,
            "features": k.features,
            "split": k.split,
            "fold": k.fold,
            "refine": k.refine,
            "budget": k.budget,
            "config_hash": k.config_hash,
            "git_sha": git_sha(),
            "data_hash": k.data_hash,
            "seed": k.seed,
            "accelerator": accelerator,
            "fold_ids": json.dumps({"train": list(fold.train), "test": list(fold.test)}),
            **({"overrides": json.dumps(list(overrides))} if overrides is not None else {}),
            "machine": machine(accelerator),
            "versions": versions(),
            **({"slurm_job": job} if job else {}),
        }

    @staticmethod
    def params(config: dict) -> dict[str, str]:
        """The run's params as the UI lists them: the resolved config flattened, a list as one value, the
        tracking settings left out (they say where a run is kept, not what it is)."""
        return {k: v for k, v in flatten(config, lists=False).items() if k.split(".")[0] != "tracking"}

    @staticmethod
    def per_mesh_csv(rows: list[dict]) -> str:
        """The per-mesh table (PER_MESH) as its file holds it: PER_MESH_COLUMNS, in that order."""
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=list(FoldRecord.PER_MESH_COLUMNS))
        writer.writeheader()
        writer.writerows(rows)
        return buf.getvalue()

    @staticmethod
    def read_per_mesh(path) -> list[dict]:
        """The rows of a per-mesh table file (PER_MESH): the mesh id a string, faces an integer, the rest floats."""
        with open(path, newline="") as f:
            return [
                {k: (v if k == "mesh" else int(v) if k == "faces" else float(v)) for k, v in row.items()}
                for row in csv.DictReader(f)
            ]

    @staticmethod
    def predictions(meshes, probabilities, raw, labels) -> dict[str, np.ndarray]:
        """The per-face arrays of every test mesh, keyed `<prefix><mesh id>` (PREDICTION_ARRAYS)."""
        out = {}
        for m, p, r, lab in zip(meshes, probabilities, raw, labels):
            out.update({f"labels_{m.id}": lab, f"labels_raw_{m.id}": r, f"probs_{m.id}": p})
        return out

    @staticmethod
    def prediction_arrays(predictions: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The per-face arrays, each cast to the dtype PREDICTION_ARRAYS gives its key's prefix."""
        out = {}
        for key, a in predictions.items():
            prefix = max((p for p in FoldRecord.PREDICTION_ARRAYS if key.startswith(p)), key=len, default=None)
            if prefix is None:
                raise KeyError(
                    f"prediction array {key!r} is not in the fold record: {list(FoldRecord.PREDICTION_ARRAYS)}"
                )
            out[key] = np.asarray(a).astype(FoldRecord.PREDICTION_ARRAYS[prefix], copy=False)
        return out
