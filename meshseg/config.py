"""A run's configuration (conf/run.yaml) composed again from its overrides: the one way the report, its
publishing and `meshseg.results` rebuild the config `meshseg.run` gave a run."""

from __future__ import annotations

import copy
import functools
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from omegaconf import DictConfig

from meshseg import CONF_DIR
from meshseg.errors import ConfigError


@contextmanager
def hydra_scope() -> Iterator[None]:
    """Hydra's compose API on conf/. Inside a Hydra app (the report's own) Hydra is initialised already,
    on the same config folder, and a second initialisation would be refused: compose there."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        yield
        return
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        yield


def run_config(overrides) -> DictConfig:
    """The config `meshseg.run` composes for `overrides` (unresolved), a copy of its own. Overrides that do not
    compose are one ConfigError: Hydra's message on one line, without its config search path.

    Composed once a process for each overrides and config search path: Hydra takes about half a second a
    config, and a report asks for each column's three times (what to import, which runs, the cells)."""
    return copy.deepcopy(_composed(tuple(overrides), _sources()))


@functools.lru_cache(maxsize=256)
def _composed(overrides: tuple[str, ...], sources: tuple) -> DictConfig:
    from hydra import compose
    from hydra.errors import HydraException

    try:
        with hydra_scope():
            return typed_like_defaults(compose("run", overrides=list(overrides)), overrides)
    except HydraException as e:
        raise ConfigError(" ".join(str(e).split("\nConfig search path")[0].split())) from None


def _sources() -> tuple:
    """Where compose looks for configs now: the running Hydra app's search path (a method in a folder of its own,
    docs/adding-a-method.md), or () for conf/ alone (hydra_scope)."""
    from hydra.core.global_hydra import GlobalHydra

    hydra = GlobalHydra.instance()
    if not hydra.is_initialized():
        return ()
    return tuple((s.provider, s.path) for s in hydra.config_loader().get_sources())


def typed_like_defaults(cfg: DictConfig, overrides: Iterable[str]) -> DictConfig:
    """`cfg`, where a value override wrote a number of the other kind than the value it replaces, with the
    override's number in the replaced value's kind, when that is exact: refine.lam=2 is refine.lam=2.0 and
    budget.epochs=15.0 is budget.epochs=15. So one setting has one config hash however it is typed (the
    hash sees 2 and 2.0 as different values). The values replaced are those the group choices alone
    (model=..., budget=...) compose. Numbers inside a list or dict, and a number where the default is null
    or not a number, stay as typed."""
    from hydra import compose
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from omegaconf import OmegaConf

    parsed = OverridesParser.create().parse_overrides(list(overrides))
    groups = [o.input_line for o in parsed if (Path(CONF_DIR) / o.key_or_group).is_dir()]  # a method's, too
    numbers = [
        (o.key_or_group, o.value())
        for o in parsed
        if not o.is_delete() and type(o.value()) in (int, float) and not o.key_or_group.startswith("hydra.")
    ]
    if not numbers:
        return cfg
    with hydra_scope():
        defaults = compose("run", overrides=[*groups, *_search_path(parsed)])
    for key, value in numbers:
        current = OmegaConf.select(cfg, key, default=None)
        if type(current) is not type(value) or current != value:
            continue  # a later override of the key (or a delete) decided its value
        replaced = OmegaConf.select(defaults, key, default=None)
        if type(replaced) is float and type(value) is int:
            OmegaConf.update(cfg, key, float(value))
        elif type(replaced) is int and type(value) is float and value.is_integer():
            OmegaConf.update(cfg, key, int(value))
    return cfg


def _search_path(parsed) -> list[str]:
    """The `hydra.searchpath` override the group choices compose with: the overrides' own, else the running
    Hydra app's (a method added in a folder of its own, docs/adding-a-method.md, is found only there)."""
    from hydra.core.hydra_config import HydraConfig

    given = [o.input_line for o in parsed if o.key_or_group == "hydra.searchpath"]
    if given or not HydraConfig.initialized() or not HydraConfig.get().searchpath:
        return given
    quoted = ("'" + str(p).replace("\\", "\\\\").replace("'", "\\'") + "'" for p in HydraConfig.get().searchpath)
    return [f"hydra.searchpath=[{','.join(quoted)}]"]
