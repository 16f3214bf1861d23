"""The report's and reproduce's configuration (conf/report.yaml, conf/reproduce.yaml) and their command line.

    python -m meshseg.report MANIFEST [report.key=value ...] [run overrides ...] [hydra options ...]

Both commands are Hydra apps. Their command line is split before Hydra sees it:

- the leading MANIFEST becomes `manifest=MANIFEST`;
- `report.*`, `manifest=`, `overrides=` and Hydra's flags (`--cfg job`, `-m`, ...) are the app's own;
- every other `key=value` is a *run override*: it goes, in order, into the config's `overrides` list and from
  there to every cell's run config (`budget=cpu`, `tracking.uri=...`, `dataset.root=...`) and, in reproduce,
  to the sweeps it launches;
- `hydra.*`, `hydra/...` and `paths.*` go to both (the app's own log folder and launcher, and the runs').

Run overrides cannot be Hydra overrides of the app itself: they are checked against each cell's run config
(a `dataset.root=` is valid for the PSB cells a manifest names, not for the default dataset).
"""

from __future__ import annotations

import re
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from meshseg.config import hydra_scope
from meshseg.data.io import check_output_folder
from meshseg.errors import ConfigError
from meshseg.report.claims_file import check_manifests, is_claims_file, load_claims
from meshseg.tracking import FoldRecord

#: what the table's header says each per-mesh metric is (FoldRecord.MESH_METRICS: after, before refinement)
METRIC_TEXT = dict(zip(FoldRecord.MESH_METRICS, ("after refinement", "before refinement")))
#: top-level keys of the apps' own config (everything else on the command line is a run override)
APP_KEYS = ("manifest", "overrides", "report")
#: top-level keys, and config groups, that both the app and the runs take
SHARED_KEYS = ("hydra", "paths")


def _key(arg: str) -> str:
    """The override's key without its +/~/++ prefix (`report.sets` of `+report.sets=[a]`)."""
    return arg.split("=", 1)[0].lstrip("+~")


def split_argv(argv) -> tuple[list[str], list[str]]:
    """(the app's arguments, the run overrides) of a command line; the leading MANIFEST becomes `manifest=`.
    Hydra's flags and their values (`--cfg job`, `-m`) lead the app's arguments: its parser takes the
    overrides only after them."""
    argv = list(argv)
    flags: list[str] = []
    app: list[str] = []
    runs: list[str] = []
    if argv and not argv[0].startswith("-") and "=" not in argv[0]:
        app.append(f"manifest={argv.pop(0)}")
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            flags.append(arg)
            continue
        top = re.split(r"[./@]", _key(arg), maxsplit=1)[0]
        if top in APP_KEYS:
            app.append(arg)
        elif top in SHARED_KEYS:
            app.append(arg)
            runs.append(arg)
        else:
            runs.append(arg)
    return [*flags, *app], runs


def report_keys(config_name: str) -> tuple[str, ...]:
    """The `report.*` settings an app takes (conf/<config_name>.yaml and what it includes)."""
    from hydra import compose

    with hydra_scope():
        return tuple(compose(config_name).report)


def check_report_keys(app_args, config_name: str) -> None:
    """Refuse a `report.<key>=` that the app does not take, naming the ones it does."""
    keys = report_keys(config_name)
    for arg in app_args:
        key = _key(arg)
        if key.startswith("report.") and key.split(".")[1] not in keys:
            command = "meshseg.report" if config_name == "report" else f"meshseg.{config_name}"
            raise ConfigError(
                f"unknown report setting {key.split('.')[1]!r} in {arg!r}: {command} takes "
                f"{', '.join('report.' + k for k in keys)}"
            )


def _quoted(value: str) -> str:
    """`value` as a single-quoted string of Hydra's override grammar: a backslash run before a quote, or at
    the end, is doubled and the quote escaped, so that any override text passes through unchanged."""
    value = re.sub(r"(\\*)'", lambda m: m.group(1) * 2 + "\\'", value)
    value = re.sub(r"(\\+)$", lambda m: m.group(1) * 2, value)
    return f"'{value}'"


def hydra_argv(argv, config_name: str) -> list[str]:
    """A command line as the Hydra app `config_name` takes it: the app's arguments, then the run overrides
    as one `overrides=[...]` list. Unknown `report.*` keys are refused here, with the known ones."""
    app, runs = split_argv(argv)
    check_report_keys(app, config_name)
    if runs:
        if any(_key(a) == "overrides" for a in app):
            raise ConfigError("give run overrides either as arguments (budget=cpu) or as overrides=[...], not both")
        app.append("overrides=[" + ",".join(_quoted(r) for r in runs) + "]")
    return app


def compose_config(config_name: str, manifest, args=()) -> DictConfig:
    """The app's config for MANIFEST and a command line's other arguments, as the Hydra app would have it
    (the Python API of `meshseg.report` / `meshseg.reproduce`)."""
    from hydra import compose
    from hydra.errors import HydraException

    overrides = [a for a in hydra_argv([str(manifest), *args], config_name) if not a.startswith("-")]
    try:
        with hydra_scope():
            return compose(config_name, overrides=overrides)
    except HydraException as e:
        raise ConfigError(str(e).split("\nConfig search path")[0].strip()) from None


def run_overrides(cfg: DictConfig) -> list[str]:
    """The run overrides of an app's config, verbatim (interpolations in them are the runs' to resolve)."""
    return [str(o) for o in OmegaConf.to_container(cfg.overrides, resolve=False)]


def _pairs(value) -> bool:
    """Whether report.paired is one pair of column keys or a list of pairs (an empty one: no comparison)."""
    pair = lambda p: isinstance(p, ListConfig) and len(p) == 2 and all(isinstance(k, str) for k in p)  # noqa: E731
    return isinstance(value, ListConfig) and (pair(value) or all(pair(p) for p in value))


def check_config(cfg: DictConfig) -> None:
    """Settings no YAML can check, in the order a user meets them; each message says what is allowed."""
    if OmegaConf.is_missing(cfg, "manifest") or not str(cfg.manifest):
        raise ConfigError("no manifest: give one first, e.g. python -m meshseg.report experiments/synthetic.yaml")
    if not isinstance(cfg.overrides, ListConfig):
        raise ConfigError(f"overrides={cfg.overrides} must be a list of run overrides")
    _check_statistics(cfg.report)
    _check_folders(cfg.report)
    _check_selection(cfg.report)
    for key in ("log", "boundaries", *(("dry_run",) if "dry_run" in cfg.report else ())):
        if not isinstance(cfg.report[key], bool):
            raise ConfigError(f"report.{key}={cfg.report[key]} must be true or false")
    if is_claims_file(cfg.manifest):  # the tables its claims name, before the first of them is built
        check_manifests(load_claims(cfg.manifest))


def _count(value, least: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def _check_statistics(s: DictConfig) -> None:
    """report.metric and the bootstrap's settings."""
    if s.metric not in FoldRecord.MESH_METRICS:
        choices = ", ".join(f"{k} ({text})" for k, text in METRIC_TEXT.items())
        raise ConfigError(f"report.metric={s.metric} is not allowed: choose {choices}")
    if not _count(s.n_boot, 1):
        raise ConfigError(f"report.n_boot={s.n_boot} must be an integer >= 1")
    if not (isinstance(s.level, (int, float)) and 0 < s.level < 1):
        raise ConfigError(f"report.level={s.level} must be a number between 0 and 1 (0.95: a 95 % interval)")
    if not _count(s.seed, 0):
        raise ConfigError(f"report.seed={s.seed} must be an integer >= 0")


def _check_folders(s: DictConfig) -> None:
    """The output and input folders, before any table is built (a bad path is no reason to read every run first)."""
    if s.get("results") not in (None, "results") and not Path(str(s.results)).is_dir():
        raise ConfigError(f"report.results={s.results}: no such folder of results records (null: import none)")
    check_output_folder(s.out_dir, "report.out_dir")


def _check_selection(s: DictConfig) -> None:
    """report.sets, report.columns and report.paired: lists of the right shape (the table checks the names)."""
    if s.sets is not None and not isinstance(s.sets, ListConfig):
        raise ConfigError(f"report.sets={s.sets} must be a list of set or category names, e.g. report.sets=[Teddy]")
    if s.get("columns") is not None and not (
        isinstance(s.columns, ListConfig) and len(s.columns) and all(isinstance(k, str) for k in s.columns)
    ):
        raise ConfigError(f"report.columns={s.columns} must be a list of column keys, e.g. report.columns=[3B,ToG15]")
    if s.paired is not None and not _pairs(s.paired):
        raise ConfigError(
            f"report.paired={s.paired} must be two column keys, e.g. report.paired=[cnn1d,K2010], or a list of "
            "such pairs, e.g. [[3B,1B],[1B,ToG15]] ([] for none)"
        )
