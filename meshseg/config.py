"""A run's configuration (conf/run.yaml) composed again from its overrides: the one way the report, its
publishing and `meshseg.results` rebuild the config `meshseg.run` gave a run."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

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
    """The config `meshseg.run` composes for `overrides` (unresolved). Overrides that do not compose are one
    ConfigError: Hydra's message on one line, without its config search path."""
    from hydra import compose
    from hydra.errors import HydraException

    try:
        with hydra_scope():
            return compose("run", overrides=list(overrides))
    except HydraException as e:
        raise ConfigError(" ".join(str(e).split("\nConfig search path")[0].split())) from None
