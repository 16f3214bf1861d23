"""One way to plug in a method: a split protocol, a model (its fitter) or a refinement is a class named
by `_target_` in its YAML, built here. Adding a method is one class plus one YAML file.

The keys `name` and `branches` of such a node are the run's (its tags and its multi-scale inputs), not
the class's: they are not passed to the constructor.
"""

from __future__ import annotations

import inspect

from hydra.errors import InstantiationException
from hydra.utils import get_object, instantiate
from omegaconf import DictConfig, OmegaConf

from meshseg.errors import ConfigError, MeshsegError

RUN_KEYS = ("name", "branches")


def build(node, setting: str, **kwargs):
    """The object `node` (a config with `_target_`) describes, with `kwargs` (run objects such as the
    training context) added to its arguments. A missing or unknown class, or a setting the class does
    not take, is one `ConfigError` naming `setting` (e.g. `model=cnn1d`); errors the class raises for
    its own values pass through."""
    if not isinstance(node, DictConfig) or "_target_" not in node:
        raise ConfigError(f"{setting}: the config names no class (`_target_:`)")
    args = OmegaConf.masked_copy(node, [k for k in node if k not in RUN_KEYS])
    try:
        # a partial: run objects are passed to the call, never merged into (and converted by) the config
        factory = instantiate(args, _partial_=True)
    except InstantiationException as e:
        cause = e.__cause__
        if isinstance(cause, MeshsegError):
            raise cause from None
        reason = str(e).strip().splitlines()[0] if cause is None else f"{type(cause).__name__}: {cause}"
        raise ConfigError(f"{setting}: cannot build {node._target_}: {reason}") from None
    given = [k for k in args if not str(k).startswith("_")]
    try:
        inspect.signature(get_object(node._target_)).bind(**dict.fromkeys(given), **kwargs)
    except TypeError as e:  # a setting the class does not take (a typo in the YAML), or one it lacks
        raise ConfigError(f"{setting}: {node._target_} does not take its settings {sorted(given)}: {e}") from None
    return factory(**kwargs)
