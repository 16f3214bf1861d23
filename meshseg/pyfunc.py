"""A fold's model as an MLflow model: a `pyfunc` that labels a mesh given as vertices and faces.

    import mlflow
    mlflow.set_tracking_uri("sqlite:///mlruns/mlflow.db")  # the runs' store (tracking.uri)
    model = mlflow.pyfunc.load_model("runs:/<run id>/model")
    out = model.predict({"vertices": V, "faces": F})  # V float64 (n, 3); F int64 (m, 3), 0-based
    out["label_name"]  # one row per face: the label meshseg.predict writes; "label" its index, "label_raw" unrefined

Every fold run logs it as the run's MLflow logged model `model` (the run's Logged models; the experiment's
Models tab). It wraps meshseg.predict's FoldModel, kept inside as artifacts/fold_model/ (the files that runs made
before logged models kept as their `model/` artifact), and runs the same path: features (cached by the mesh's
content hash; `params={"cache_dir": DIR}` keeps them between calls, else a temporary folder), X^1..X^B,
standardised, the model's probabilities, the refinement. Loading it needs the meshseg package importable (this
repository, `pip install -e .`) and downloads nothing: its pip requirements are meshseg's own dependencies at the
versions it was trained with, written down rather than inferred (MLflow infers them by loading the model in a
subprocess). `fold_model/model.pt` is a pickle: load models from stores you trust.
"""

from __future__ import annotations

import functools
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import mlflow.pyfunc
import numpy as np

from meshseg.errors import MeshDataError, MeshsegError
from meshseg.predict import FoldModel
from meshseg.tracking import FoldRecord

#: the script MLflow logs as the model's code (MLflow's "models from code": no pickled wrapper)
CODE = Path(__file__).with_name("pyfunc_model.py")
#: the feature cache of the fold whose model is being logged: MLflow checks a logged model by predicting its
#: input example, and the example's features are then computed once per cache, not once per fold
_LOGGING = {"cache_dir": None}


class FoldPyfunc(mlflow.pyfunc.PythonModel):
    """meshseg.predict's FoldModel as an MLflow pyfunc: `predict({"vertices": V, "faces": F})`, a row per face."""

    # MLflow asks a PythonModel for type hints on `predict` to infer its signature from (a warning in every process
    # otherwise); none can say "a dict of two arrays", so the signature is given when the model is logged instead
    _skip_type_hint_validation = True

    def load_context(self, context) -> None:
        self.model = FoldModel.load(Path(context.artifacts[FoldModel.FOLDER]))

    def predict(self, context, model_input, params=None):
        import pandas as pd
        from mlflow.exceptions import MlflowException
        from mlflow.protos.databricks_pb2 import INVALID_PARAMETER_VALUE

        from meshseg.data.mesh import Mesh

        try:
            if not (hasattr(model_input, "keys") and {"vertices", "faces"} <= set(model_input.keys())):
                raise MeshDataError("the model input", "must hold 'vertices' (n, 3) and 'faces' (m, 3)")
            mesh = Mesh(model_input["vertices"], model_input["faces"], source="the model input")
            with feature_cache((params or {}).get("cache_dir")) as cache:
                _, raw, labels = self.model.predict(mesh, cache)
        except MeshsegError as e:  # the caller's mesh, not the server: MLflow's scoring server answers 400 with it
            raise MlflowException(str(e), error_code=INVALID_PARAMETER_VALUE) from None
        names = np.asarray(self.model.label_names, dtype=object)[labels]
        return pd.DataFrame({"label": labels.astype(np.int64), "label_raw": raw.astype(np.int64), "label_name": names})


@contextmanager
def feature_cache(folder: str | None) -> Iterator[str]:
    """The feature cache a prediction uses: `folder`, the logging fold's, or a temporary one."""
    folder = folder or _LOGGING["cache_dir"]
    if folder:
        yield folder
        return
    with tempfile.TemporaryDirectory(prefix="meshseg-features-") as tmp:
        yield tmp


def signature():
    """Input: the mesh, as tensors `vertices` (float64, n x 3) and `faces` (int64, m x 3); param `cache_dir`;
    output: per face `label` (index into the label names), `label_raw` (before refinement), `label_name`."""
    from mlflow.models import ModelSignature
    from mlflow.types.schema import ColSpec, ParamSchema, ParamSpec, Schema, TensorSpec

    return ModelSignature(
        inputs=Schema(
            [TensorSpec(np.dtype(np.float64), (-1, 3), "vertices"), TensorSpec(np.dtype(np.int64), (-1, 3), "faces")]
        ),
        outputs=Schema([ColSpec("long", "label"), ColSpec("long", "label_raw"), ColSpec("string", "label_name")]),
        params=ParamSchema([ParamSpec("cache_dir", "string", "")]),
    )


def example_mesh() -> dict[str, np.ndarray]:
    """The input example: an ellipsoid of 80 faces (an icosahedron subdivided once), small enough that MLflow's
    check of the logged model (it predicts the example) costs little."""
    t = (1 + 5**0.5) / 2
    corners = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t)]
    corners += [(0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    icosahedron = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2)]
    icosahedron += [(10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5)]
    icosahedron += [(2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    vertices, middle, faces = [np.array(c, dtype=np.float64) for c in corners], {}, []

    def mid(a: int, b: int) -> int:
        if (a, b) not in middle:
            vertices.append(vertices[a] + vertices[b])
            middle[a, b] = middle[b, a] = len(vertices) - 1
        return middle[a, b]

    for a, b, c in icosahedron:
        ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
        faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
    V = np.array([v / np.linalg.norm(v) for v in vertices]) * (1.0, 0.6, 1.6)
    return {"vertices": V.round(6), "faces": np.array(faces, dtype=np.int64)}


@functools.cache  # the same for every fold of a process, and reading package metadata is slow
def requirements() -> tuple[str, ...]:
    """meshseg's own dependencies (not its extras), pinned at the versions installed here."""
    from importlib.metadata import PackageNotFoundError, requires, version

    from packaging.requirements import Requirement

    try:
        wanted = [Requirement(r) for r in requires("meshseg") or []]
    except PackageNotFoundError:  # a checkout on the path, not installed
        wanted = [Requirement(n) for n in ("mlflow", "torch", "numpy", "scipy", "scikit-learn", "pytorch-lightning")]
    out = []
    for req in wanted:
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        try:
            out.append(f"{req.name}=={version(req.name).split('+')[0]}")  # torch 2.13.0+cpu: pip knows 2.13.0
        except PackageNotFoundError:
            out.append(str(req))
    return tuple(out)


#: the run tags a fold's saved model carries along (its model.yaml says where it came from)
ABOUT_MODEL = ("dataset", "category", "fold", "model", "branches", "features", "budget", "config_hash", "git_sha")


def log_fold_model(tracker, run_id: str, job, preds, refine_settings: dict) -> str:
    """The fold's model (meshseg.predict.FoldModel: `job`'s config, the fitted `preds` and the refinement settings
    it chose) as run `run_id`'s MLflow logged model FoldRecord.MODEL (`tracker`: a meshseg.tracking.Tracker); its
    id. The input example's features are kept in the fold's feature cache."""
    about = {"run_id": run_id, **{k: job.tags[k] for k in ABOUT_MODEL}}
    label_names = job.dataset.label_names(job.key.category)
    model = FoldModel.of_fold(job.config, preds, label_names, about, refine_settings)
    cache_dir = job.cache_dir

    def save(model_id: str) -> None:
        os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # MLflow's check downloads the model
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp) / FoldModel.FOLDER
            model.save(folder)
            _LOGGING["cache_dir"] = cache_dir
            try:
                mlflow.pyfunc.log_model(
                    name=FoldRecord.MODEL,
                    python_model=str(CODE),
                    artifacts={FoldModel.FOLDER: str(folder)},
                    signature=signature(),
                    input_example=example_mesh(),
                    pip_requirements=list(requirements()),
                    metadata={"meshseg": {**model.about, "label_names": list(model.label_names)}},
                    model_id=model_id,
                )
            finally:
                _LOGGING["cache_dir"] = None

    return tracker.log_model(run_id, save, {k: v for k, v in model.about.items() if k != "run_id"})
