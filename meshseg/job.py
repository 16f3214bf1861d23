"""One fold's job: everything its run needs, resolved from the run config and checked once, before any
feature is computed or any run created. Below this module no layer sees the run config: the builders get
their own (resolved) node (dataset, split, features, model, refinement), everything else plain values and
built objects."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from meshseg import CONF_DIR
from meshseg.config import typed_like_defaults
from meshseg.data.datasets import MeshDataset, build_dataset
from meshseg.data.splits import Fold, build_split
from meshseg.errors import ConfigError
from meshseg.features.sets import FeatureSet
from meshseg.refine import build_refinement

log = logging.getLogger("meshseg.run")

BRANCHES = (1, 2, 3, 4)
RING_ADJACENCY = ("edge", "vertex")
RESAMPLE = ("fold", "epoch")  # budget.resample
CHECKPOINTS = (True, False, "auto")  # tracking.checkpoints


@dataclass
class FoldOutcome:
    """What one fold's job did (a sweep's closing summary counts them): its test accuracy (area-weighted,
    refined; NaN for a fold another live run holds), and whether it was skipped."""

    category: str
    fold: int
    acc: float
    skipped: bool


@dataclass(frozen=True)
class FoldJob:
    """A fold resolved: the data it trains and tests on, the method's parts (built, not fitted), and how
    its run is recorded. `config` is the fold's resolved config, its identity (`key.config_hash`)."""

    key: object  # meshseg.tracking.RunKey: its identity (config hash), tags and name
    dataset: MeshDataset
    fold: Fold
    features: FeatureSet
    fitter: object  # meshseg.training.fitters.Fitter, built (its settings checked), not fitted
    refinement: object  # meshseg.refine.Refinement
    branches: int
    ring_adjacency: str
    faces_per_mesh: int | None
    workers: int
    cache_dir: str
    checkpoints: Path | None  # per-epoch checkpoints (a killed fold resumes from them), or none
    tracking: dict  # the tracking settings (store, leases, what to log)
    config: dict
    tags: dict

    def skipped(self, holder) -> FoldOutcome:
        """Log why the fold is not run (its config is FINISHED, or a live process runs it): `holder` is that
        run. Its outcome: the holder's accuracy, or NaN."""
        from meshseg.tracking import FoldRecord

        key, info = self.key, holder.info
        acc = holder.data.metrics.get(FoldRecord.ACC, float("nan"))
        if info.status == "FINISHED":
            log.info(
                "skip: %s — config %s already has FINISHED run %s (test/acc %.4f)",
                key.name,
                key.config_hash,
                info.run_id,
                acc,
            )
        else:
            owner = holder.data.tags.get("lease.owner", "?")
            log.info("skip: %s — config %s is being run by run %s (%s)", key.name, key.config_hash, info.run_id, owner)
        return FoldOutcome(key.category, key.fold, acc, True)

    @classmethod
    def from_config(cls, cfg: DictConfig, overrides: list[str] | None = None) -> FoldJob:
        """The fold job a run config describes, every setting checked; nothing computed, no run created.
        `overrides`: the command line's (recorded as provenance)."""
        from meshseg.tracking import FoldRecord, RunKey, fold_identity

        if overrides:
            cfg = typed_like_defaults(cfg, overrides)  # refine.lam=2 is refine.lam=2.0: one identity
        check_config(cfg)
        # resolved once (${...} evaluated): the parts are built from the very values the identity hashes
        run = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
        dataset = build_dataset(run.dataset)
        method = build_method(run)
        category, fold = resolve_fold(run, dataset, method.split)
        method.fitter.check_fold(len(fold.train))
        config, chash = fold_identity(run, category, fold, dataset.data_hash)
        key = RunKey(
            dataset=dataset.name,
            category=category,
            model=run.model.name,
            branches=run.branches,
            features=method.features.name,
            split=method.split.name,
            fold=fold.index,
            refine=run.refine.name,
            budget=run.budget.name,
            config_hash=chash,
            data_hash=dataset.data_hash,
            seed=run.seed,
        )
        return cls(
            key=key,
            dataset=dataset,
            fold=fold,
            features=method.features,
            fitter=method.fitter,
            refinement=method.refinement,
            branches=run.branches,
            ring_adjacency=run.ring_adjacency,
            faces_per_mesh=run.budget.faces_per_mesh,
            workers=run.workers,
            cache_dir=run.paths.cache_dir,
            checkpoints=checkpoint_dir(run, chash),
            tracking=config["tracking"],
            config=config,
            tags=FoldRecord.tags(key, fold, accelerator=run.trainer.accelerator, overrides=overrides),
        )


def known_settings() -> tuple[str, ...]:
    """The top-level keys a run config may have: conf/run.yaml's groups and its own keys."""
    import yaml

    primary = yaml.safe_load((Path(CONF_DIR) / "run.yaml").read_text())
    groups = [next(iter(d)) if isinstance(d, dict) else d for d in primary["defaults"]]
    keys = [*(g for g in groups if g != "_self_" and not g.startswith("override ")), *primary]
    return tuple(k for k in dict.fromkeys(keys) if k not in ("defaults", "hydra"))


def check_settings(keys) -> None:
    """Refuse a top-level key no config group or setting uses (`+modle=cnn1d` would otherwise train the
    default model with a junk key in its config hash), suggesting the nearest known one."""
    import difflib

    known = known_settings()
    for key in keys:
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1)
            hint = f" (did you mean {near[0]}?)" if near else ""
            raise ConfigError(f"unknown setting {key!r}{hint}: meshseg.run takes {', '.join(known)}")


#: Hydra's flags whose next argument is their value, not an override
_VALUE_FLAGS = {
    *("-sc", "--shell-completion", "-cp", "--config-path", "-cn", "--config-name", "-cd", "--config-dir"),
    *("-c", "--cfg", "-p", "--package", "--experimental-rerun"),
}


def check_argv(argv: list[str]) -> None:
    """`check_settings` on the command line's overrides, before Hydra suggests `+key=` for a typo."""
    keys, flag_value = [], False
    for arg in argv:
        if flag_value or arg.startswith("-") or "=" not in arg:
            # -m, --flags, and the value of a flag that takes one (`-sc install=bash` is no setting)
            flag_value = arg in _VALUE_FLAGS
            continue
        key = arg.split("=", 1)[0].lstrip("+~").split(".")[0].split("/")[0].split("@")[0]
        if key != "hydra":
            keys.append(key)
    check_settings(keys)


#: more faces than any mesh has: a larger number means every face, which null says under one config hash
MAX_FACES_PER_MESH = 10_000_000


def _whole(v, low: int, high: float = float("inf")) -> bool:
    """An integer (not a bool, not 64.5, not "abc") within [low, high]."""
    return isinstance(v, int) and not isinstance(v, bool) and low <= v <= high


def check_config(cfg: DictConfig) -> None:
    """Every run setting no config group checks for itself; each message lists what is allowed."""
    check_settings([k for k in cfg.keys() if k != "hydra"])  # a sweep job's config carries hydra's own node
    if cfg.branches not in BRANCHES:
        raise ConfigError(f"branches={cfg.branches} is not allowed: choose one of {list(BRANCHES)}")
    fixed = cfg.model.get("branches")
    if fixed is not None and cfg.branches != fixed:
        raise ConfigError(
            f"branches={cfg.branches} is not allowed with model={cfg.model.name}: it takes branches={fixed}"
        )
    if cfg.ring_adjacency not in RING_ADJACENCY:
        raise ConfigError(f"ring_adjacency={cfg.ring_adjacency} is not allowed: choose one of {list(RING_ADJACENCY)}")
    b = cfg.budget
    for key in ("epochs", "batch_size"):
        if not _whole(b[key], 1):
            raise ConfigError(f"budget.{key}={b[key]} is not allowed (budget {b.name}): it must be an integer >= 1")
    if not (b.faces_per_mesh is None or _whole(b.faces_per_mesh, 1, MAX_FACES_PER_MESH)):
        raise ConfigError(
            f"budget.faces_per_mesh={b.faces_per_mesh} is not allowed (budget {b.name}): it must be an integer "
            f"from 1 to {MAX_FACES_PER_MESH:,}, or null for every face"
        )
    if b.get("resample", "fold") not in RESAMPLE:
        raise ConfigError(f"budget.resample={b.resample} is not allowed: choose one of {list(RESAMPLE)}")
    if not (isinstance(cfg.seed, int) and isinstance(cfg.workers, int) and cfg.workers >= 1):
        raise ConfigError(f"seed={cfg.seed} must be an integer and workers={cfg.workers} an integer >= 1")
    if cfg.tracking.get("checkpoints", "auto") not in CHECKPOINTS:
        raise ConfigError(f"tracking.checkpoints={cfg.tracking.checkpoints} is not allowed: choose auto, true or false")
    t = cfg.tracking
    if not (float(t.heartbeat_s) > 0 and float(t.lease_timeout_s) > 2 * float(t.heartbeat_s)):
        raise ConfigError(
            f"tracking.heartbeat_s={t.heartbeat_s} must be > 0 and tracking.lease_timeout_s="
            f"{t.lease_timeout_s} more than twice it"
        )


@dataclass(frozen=True)
class Method:
    """The parts a run config's method is made of, built (which checks their settings: a network's, a
    feature group's, a refinement's, the training context's) and not yet fitted."""

    split: object  # meshseg.data.splits.SplitProtocol
    features: FeatureSet
    fitter: object  # meshseg.training.fitters.Fitter; its context gets the run's logger once the run exists
    refinement: object  # meshseg.refine.Refinement


def build_method(cfg: DictConfig) -> Method:
    """The method's parts, built once per fold, before any feature is computed or run created."""
    from meshseg.training.context import TrainContext
    from meshseg.training.fitters import build_fitter

    fitter = build_fitter(cfg.model, TrainContext.from_config(cfg.budget, cfg.trainer, cfg.seed))
    refinement = build_refinement(cfg.refine)
    if refinement.search is not None and not fitter.holds_out_meshes:
        raise ConfigError(
            f"refine.search is not allowed with model={cfg.model.name}: it chooses on training meshes the model "
            "holds out and predicts without them, as model=gbdt does"
        )
    return Method(build_split(cfg.split), FeatureSet.from_config(cfg.features), fitter, refinement)


def checkpoint_dir(cfg: DictConfig, config_hash: str) -> Path | None:
    """Where a fold keeps its per-epoch checkpoints (`tracking.checkpoints`: auto = at budget=paper, where a
    fold trains for hours), keyed by its config hash so that the rerun of a killed fold finds them."""
    on = cfg.tracking.get("checkpoints", "auto")
    if on is False or (on == "auto" and cfg.budget.name != "paper"):
        return None
    return Path(cfg.paths.cache_dir) / "checkpoints" / config_hash


def resolve_fold(cfg: DictConfig, dataset: MeshDataset, split) -> tuple[str, Fold]:
    """The run's category (default: the dataset's first) and fold (default: 0), checked."""
    category = dataset.check_category(cfg.category) if cfg.category is not None else dataset.categories[0]
    folds = split.folds(dataset, category)
    index = 0 if cfg.fold is None else cfg.fold
    if not (isinstance(index, int) and 0 <= index < len(folds)):
        raise ConfigError(
            f"fold={cfg.fold} is out of range: split {split.name} of {category} has folds 0..{len(folds) - 1}"
        )
    return category, folds[index]
