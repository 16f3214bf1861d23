"""A run's identity: its resolved config flattened and hashed (DESIGN "Tracking contract"). A config
whose hash already has a FINISHED run is not run again."""

from __future__ import annotations

import hashlib
import json


def flatten(node, prefix: str = "", lists: bool = True) -> dict[str, object]:
    """{"a.b.c": leaf} for nested dicts and lists (list items keyed by index; with lists=False a list is
    one leaf, written as JSON)."""
    if isinstance(node, list) and not lists:
        return {prefix: json.dumps(node, default=str)}
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else None
    if items is None:
        return {prefix: node}
    out: dict[str, object] = {}
    for k, v in items:
        out.update(flatten(v, f"{prefix}.{k}" if prefix else str(k), lists))
    return out


def config_hash(config: dict, exclude=(), extra: dict | None = None, defaults: dict | None = None) -> str:
    """sha256 (16 hex) of the config's leaves except the `exclude` keys (a key excludes its subtree)
    and the `defaults` leaves that hold their default value, plus `extra` (e.g. the data hash)."""
    prefixes, defaults = tuple(exclude), defaults or {}
    leaves = {
        k: v
        for k, v in flatten(config).items()
        if not any(k == p or k.startswith(p + ".") for p in prefixes) and not (k in defaults and defaults[k] == v)
    }
    blob = json.dumps({"config": leaves, "extra": extra or {}}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def fold_identity(cfg, category: str, fold, data_hash: str) -> tuple[dict, str]:
    """The resolved config of one fold's run and its config hash: what `meshseg.run` logs and skips on,
    and what the report looks runs up by. `cfg` is the composed config or its resolved dict (the
    report resolves once per column and asks for every fold). `fold` is a `meshseg.data.splits.Fold`:
    its train and test mesh ids enter the hash, so another split file, or another way of dealing
    meshes into folds, never reuses a run of a different fold."""
    from omegaconf import DictConfig, OmegaConf

    config = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    config.update(category=category, fold=fold.index)
    extra = {"data_hash": data_hash, "train": list(fold.train), "test": list(fold.test)}
    tracking = config["tracking"]
    return config, config_hash(config, tracking["hash_exclude"], extra, tracking.get("hash_defaults"))
