"""`python -m meshseg.report MANIFEST [overrides]`: a manifest's table rebuilt from the logged runs, set beside
the published numbers, written under <report.out_dir>/<manifest name>/ and logged as an MLflow run.

    python -m meshseg.report experiments/table2_psb_5fold.yaml
    python -m meshseg.report experiments/table2_psb_5fold.yaml report.sets=[Teddy] report.metric=acc_raw
    python -m meshseg.report experiments/claims.yaml    # does the paper reproduce? every claim judged (reports/claims/)
    python -m meshseg.report experiments/figures.yaml   # the paper's mesh figures from the runs (reports/figures/)

`report.*` settings: conf/report.yaml. Every other override is a run override (budget=cpu, tracking.uri=...,
dataset.root=...) applied to each cell's run config. Hydra's flags work as for meshseg.run (--cfg job).
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from meshseg import CONF_DIR
from meshseg.cli import usage, user_errors
from meshseg.config import hydra_scope
from meshseg.errors import MeshsegError
from meshseg.report.cells import Table
from meshseg.report.claims import claims_from_config, summary_table
from meshseg.report.claims_file import is_claims_file, load_claims
from meshseg.report.config import check_config, compose_config, hydra_argv
from meshseg.report.figures import figures_from_config, is_figures_file, load_figures
from meshseg.report.figures import summary as figures_summary
from meshseg.report.manifest import load_manifest
from meshseg.report.publish import build, publish, requested, summary


def report_from_config(cfg: DictConfig) -> tuple[Table, list[Path], str | None]:
    """Build, write and (unless report.log=false) log the report the app config describes."""
    check_config(cfg)
    table = build(load_manifest(cfg.manifest), cfg)
    return table, *publish(table, cfg.report)


def report(manifest_path, args=()) -> tuple[Table, list[Path], str | None]:
    """The command as a function: `args` as on the command line after MANIFEST (report.* settings and run
    overrides). Returns the table, the files written and the report's run id (None with report.log=false)."""
    return report_from_config(compose_config("report", manifest_path, args))


def run_app(argv, app, config_name: str, doc: str) -> None:
    """A report-style command: usage on -h or no arguments, the command line checked and handed to the Hydra
    app `app` of conf/<config_name>.yaml (a user error printed as one `error:` line); any other exception
    propagates."""
    argv = list(argv)
    usage(doc, argv)
    with user_errors():
        args = hydra_argv(argv, config_name)
        _check_before_hydra(args, config_name)
    saved = sys.argv
    sys.argv = [saved[0], *args]  # hydra.main reads sys.argv
    try:
        app()
    finally:
        sys.argv = saved


def _check_before_hydra(app_args, config_name: str) -> None:
    """A missing or malformed manifest (claims or figures file), or a `report.*` setting it does not allow, refused
    before Hydra makes the command's log folder. Any other exception is a bug: left for the app to meet again,
    where Hydra reports it with its traceback."""
    from hydra import compose

    path = next((a.split("=", 1)[1] for a in app_args if a.startswith("manifest=")), "")
    try:
        kind = "" if not path else "claims" if is_claims_file(path) else "figures" if is_figures_file(path) else "table"
        load = {"claims": load_claims, "figures": load_figures, "table": load_manifest}.get(kind)
        manifest = load(path) if load else None
        if not path or any(a.startswith("-") for a in app_args):
            return  # Hydra's own flags (--cfg job, -cn NAME) are the app's to read
        with hydra_scope():
            cfg = compose(config_name, overrides=list(app_args))
        check_config(cfg)
        if kind == "table":
            requested(manifest, cfg.report)
    except MeshsegError:
        raise
    except Exception:  # reported by the app, under Hydra's error handling
        pass


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="report")
def _report_app(cfg: DictConfig) -> None:
    with user_errors():
        if is_claims_file(cfg.manifest):  # experiments/claims.yaml: the paper's claims judged on the runs
            check_config(cfg)
            claims, files = claims_from_config(cfg)
            print(summary_table(claims))
            print("\n".join(f"wrote {f}" for f in files))
            return
        if is_figures_file(cfg.manifest):  # experiments/figures.yaml: the paper's figures drawn from the runs
            check_config(cfg)
            _, drawn, files = figures_from_config(cfg)
            print(figures_summary(drawn, files))
            return
        table, files, run_id = report_from_config(cfg)
    print(summary(table, files, run_id))


def main(argv=None) -> None:
    """`python -m meshseg.report`."""
    run_app(sys.argv[1:] if argv is None else argv, _report_app, "report", __doc__)
