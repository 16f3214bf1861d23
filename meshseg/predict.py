"""A fold's trained model, kept with its run, and `python -m meshseg.predict` to label any mesh with it.

    python -m meshseg.predict run_id=<id> mesh=my.off out=my_labels.txt [render=my.png] [tracking.uri=...]

Every fold run logs its model (DESIGN "Tracking contract"): `model.pt`, the fitted fitter with the
standardiser of its inputs and what turns a mesh into those inputs (feature set, branches, ring
adjacency, refinement, label names), and `model.yaml`, the same settings readable. They sit in the run's
MLflow logged model `model` (meshseg.pyfunc, which `mlflow.pyfunc.load_model` loads), as its
artifacts/fold_model/; runs made before logged models kept them as their `model/` artifact, and both are
read here. Predicting runs the run's own path: features (cached by the mesh's content hash), X^1..X^B,
standardised, the model's probabilities, the refinement. `out` ending `.seg` writes one label per face
(COSEG's integer label where the labels are integers, else the label's index); any other name writes
L-PSB's `_labels.txt` format.
`model.pt` is a pickle: load models from stores you trust.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from meshseg.cli import command, usage
from meshseg.data.mesh import Mesh
from meshseg.errors import ConfigError, MeshsegError, TrackingError

log = logging.getLogger("meshseg.predict")


@dataclasses.dataclass
class FoldModel:
    fitter: object  # a fitted meshseg.training.fitters.Fitter
    standardiser: object  # meshseg.training.data.Standardiser of the training faces
    label_names: tuple[str, ...]
    features: dict  # the run's `features` config
    branches: int
    ring_adjacency: str
    refine: dict  # the run's `refine` config
    about: dict  # where it came from: run name, dataset, category, fold, config hash, git sha

    FILE, ABOUT = "model.pt", "model.yaml"
    #: the folder of FILE and ABOUT inside the run's logged model (under its artifacts/)
    FOLDER = "fold_model"

    @classmethod
    def find(cls, folder: Path) -> Path | None:
        """Where a run's downloaded model keeps FILE: the logged model's artifacts/fold_model/, or the `model/`
        artifact itself (a run made before logged models); None when neither has it."""
        for where in (Path(folder) / "artifacts" / cls.FOLDER, Path(folder)):
            if (where / cls.FILE).is_file():
                return where
        return None

    def save(self, folder: Path) -> None:
        import torch
        import yaml

        folder.mkdir(parents=True, exist_ok=True)
        torch.save(self, folder / self.FILE)
        readable = {k: v for k, v in dataclasses.asdict(self).items() if k not in ("fitter", "standardiser")}
        readable["label_names"] = list(self.label_names)
        (folder / self.ABOUT).write_text(yaml.safe_dump(readable, sort_keys=False))

    @classmethod
    def of_fold(cls, config: dict, preds, label_names, about: dict, chosen: dict | None = None) -> FoldModel:
        """The model `meshseg.run` trained on one fold (`config`: the run's resolved config; `preds`: its
        `FoldPredictions`; `about`: where it came from; `chosen`: the refinement settings refine.search
        chose for the fold, which the model then refines with)."""
        refine = dict(config["refine"])
        if chosen:
            refine.update(chosen, search=None)
        return cls(
            preds.fitter,
            preds.standardiser,
            tuple(label_names),
            config["features"],
            int(config["branches"]),
            str(config["ring_adjacency"]),
            refine,
            dict(about),
        )

    @classmethod
    def load(cls, folder: Path) -> FoldModel:
        import torch

        path = Path(folder) / cls.FILE
        try:
            model = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:  # a truncated file, or one from code that has since changed
            raise MeshsegError(f"{path}: cannot load the model ({type(e).__name__}: {e})") from None
        if not isinstance(model, cls):
            raise MeshsegError(f"{path}: not a meshseg fold model")
        if not torch.cuda.is_available():
            model.fitter.to_cpu()
        return model

    def predict(self, mesh: Mesh, cache_root) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(probabilities (faces, classes), argmax labels, refined labels) of every face of `mesh`."""
        from omegaconf import OmegaConf

        from meshseg.features.sets import FeatureSet
        from meshseg.refine import build_refinement
        from meshseg.training.data import mesh_groups, mesh_scales

        features = FeatureSet.from_config(OmegaConf.create(self.features))
        refinement = build_refinement(OmegaConf.create(self.refine))
        scales = mesh_scales(mesh, features, cache_root, self.branches, self.ring_adjacency)
        P = self.fitter.predict_mesh(mesh, self.standardiser.transform(np.stack(scales, axis=1)))
        labels = refinement(mesh, P, mesh_groups(mesh, features, refinement.needs, cache_root))
        return P, P.argmax(axis=1), labels


def write_labels(path: str, labels: np.ndarray, names) -> None:
    """L-PSB `_labels.txt` format, or `.seg` (see the module doc)."""
    from meshseg.data.io import write_psb_labels, write_seg

    if str(path).lower().endswith(".seg"):
        numeric = all(n.lstrip("-").isdigit() for n in names)
        write_seg(path, np.asarray([int(n) for n in names])[labels] if numeric else labels)
    else:
        write_psb_labels(path, labels, names)


def download_model(tracker, run, dst: str) -> Path:
    """The run's model downloaded into `dst`: its logged model FoldRecord.MODEL (meshseg.pyfunc) or, for a run made
    before logged models, its `model/` artifact. (MLflow resolves the logged model behind `runs:/<id>/model` in the
    store of its global tracking uri, not the tracker's: it is looked up here by the run's outputs instead.)"""
    from mlflow.artifacts import download_artifacts

    from meshseg.tracking import FoldRecord

    for output in run.outputs.model_outputs if run.outputs else []:
        model = tracker.client.get_logged_model(output.model_id)
        if model.name == FoldRecord.MODEL:
            uri = model.artifact_location
            return Path(download_artifacts(artifact_uri=uri, dst_path=dst, tracking_uri=tracker.uri))
    return Path(tracker.client.download_artifacts(run.info.run_id, FoldRecord.MODEL, dst))


def load_run_model(tracker, run_id: str) -> tuple[FoldModel, object]:
    """The model a run logged, and the run; an unknown run or one without a model is one error."""
    from mlflow.exceptions import MlflowException

    from meshseg.tracking import FoldRecord

    try:
        run = tracker.client.get_run(run_id)
    except MlflowException:
        raise TrackingError(f"run_id={run_id}: no such run in {tracker.uri}") from None
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    with tempfile.TemporaryDirectory() as tmp:
        try:
            folder = FoldModel.find(download_model(tracker, run, tmp))
        except (MlflowException, OSError):
            folder = None
        if folder is None:
            raise TrackingError(
                f"run_id={run_id} ({run.info.run_name}) has no {FoldRecord.MODEL}: it ran with "
                "tracking.log_model=false, was imported from results/, or ran before runs kept their models"
            )
        try:
            return FoldModel.load(folder), run
        except MeshsegError as e:  # name the run, not the temporary download it came through
            why = str(e).split(": ", 1)[-1]
            raise TrackingError(f"run_id={run_id} ({run.info.run_name}): its {FoldRecord.MODEL} {why}") from None


def predict(cfg) -> dict:
    """Label `cfg.mesh` with run `cfg.run_id`'s model; write `cfg.out` (and `cfg.render`). Returns a summary."""
    from meshseg.data.io import check_output_file, read_mesh
    from meshseg.tracking import Tracker, check_store_exists

    if not cfg.get("run_id") or not cfg.get("mesh") or not cfg.get("out"):
        raise ConfigError("meshseg.predict needs run_id=<run id> mesh=<file .off|.obj> out=<labels file>")
    check_output_file(cfg.out, "out")  # before any work: a bad output path is no reason to label the mesh first
    if cfg.get("render"):
        check_output_file(cfg.render, "render")
    check_store_exists(cfg.tracking.uri)
    mesh = read_mesh(str(cfg.mesh))
    model, run = load_run_model(
        Tracker(cfg.tracking.uri, cfg.tracking.experiment, cfg.tracking.artifact_dir), cfg.run_id
    )
    _, raw, labels = model.predict(mesh, cfg.paths.cache_dir)
    write_labels(str(cfg.out), labels, model.label_names)
    if cfg.get("render"):
        from meshseg.render import label_comparison_png

        title = f"{mesh.id} — {run.info.run_name}"
        Path(cfg.render).write_bytes(
            label_comparison_png(mesh.vertices, mesh.faces, labels, None, model.label_names, title=title)
        )
    counts = np.bincount(labels, minlength=len(model.label_names))
    return {"run": run.info.run_name, "faces": mesh.n_faces, "labels": dict(zip(model.label_names, counts.tolist()))}


@command
def main(argv=None) -> None:
    """`python -m meshseg.predict run_id=… mesh=… out=… [render=…] [tracking.*=…] [paths.*=…]`."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from meshseg import CONF_DIR

    argv = sys.argv[1:] if argv is None else list(argv)
    usage(__doc__.strip().split("\n\n")[1], argv)
    own_keys = ("run_id", "mesh", "out", "render")
    own = {k: v for k, _, v in (a.partition("=") for a in argv) if k in own_keys}
    overrides = [a for a in argv if a.partition("=")[0] not in own_keys]
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if bad := [a for a in overrides if not a.startswith(("tracking.", "paths."))]:
        raise ConfigError(f"meshseg.predict takes {', '.join(own_keys)}, tracking.* and paths.*, not {bad[0]!r}")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("run", overrides=overrides)
    OmegaConf.set_struct(cfg, False)
    summary = predict(OmegaConf.merge(cfg, own))
    log.info(
        "%s: %d faces labelled with %s -> %s %s",
        own["mesh"],
        summary["faces"],
        summary["run"],
        own["out"],
        summary["labels"],
    )


if __name__ == "__main__":
    from meshseg.predict import main as _main  # the module's own classes, not __main__'s (model.pt names them)

    _main()
