"""The report: a manifest's table rebuilt from the logged runs and set beside the published numbers
(Markdown, LaTeX, HTML, CSV, PNG under reports/<manifest>/), itself logged as an MLflow run.

    python -m meshseg.report experiments/table2_psb_5fold.yaml budget=cpu
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from meshseg import CONF_DIR
from meshseg.report.manifest import Manifest, ManifestError, load_manifest
from meshseg.report.table import Table, collect
from meshseg.report.write import markdown, write_report

__all__ = ["ManifestError", "Manifest", "Table", "load_manifest", "collect", "write_report", "split_overrides", "publish", "summary", "report"]


def split_overrides(args) -> tuple[DictConfig, list[str]]:
    """`report.key=value` overrides set conf/report.yaml; the others are run overrides."""
    settings = OmegaConf.load(Path(CONF_DIR) / "report.yaml")
    run_overrides = []
    for a in args:
        if a.startswith("report."):
            key, _, value = a[len("report."):].partition("=")
            if key not in settings:
                raise ValueError(f"unknown report setting {key!r}: choose one of {list(settings)}")
            OmegaConf.update(settings, key, OmegaConf.create(f"v: {value}").v if value else None)
        else:
            run_overrides.append(a)
    if settings.metric not in ("acc", "acc_raw"):
        raise ValueError(f"report.metric={settings.metric} is not allowed: choose acc (after refinement) or acc_raw")
    return settings, run_overrides


def build(manifest: Manifest, run_overrides, settings: DictConfig) -> Table:
    return collect(manifest, run_overrides, metric=settings.metric, n_boot=int(settings.n_boot),
                   level=float(settings.level), seed=int(settings.seed), sets=settings.sets)


def log_report(table: Table, files: list[Path], settings: DictConfig) -> str:
    """Log the report as a run of experiment `settings.experiment` in the runs' store: its files as
    artifacts, each complete average as a metric. Returns the run id."""
    from hydra import compose, initialize_config_dir

    from meshseg.tracking import Tracker, git_sha

    m = table.manifest
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("run", overrides=[*m.overrides, *table.overrides])
    tracker = Tracker(cfg.tracking.uri, settings.experiment, cfg.tracking.artifact_dir)
    ident = hashlib.sha256(repr((m.name, table.overrides, OmegaConf.to_yaml(settings))).encode()).hexdigest()[:16]
    tags = {"report": m.name, "budget": ",".join(table.budgets), "config_hash": ident, "git_sha": git_sha(),
            "manifest": str(m.path)}
    cells = [c for r in table.rows for c in r.cells if c.status != "published"]
    metrics = {"cells_ok": sum(c.status == "ok" for c in cells), "cells_incomplete": sum(c.status == "incomplete" for c in cells),
               "cells_unavailable": sum(c.status == "unavailable" for c in cells)}
    for row in table.rows:
        for c in row.cells:
            if row.kind != "set" and c.value is not None:
                metrics[re.sub(r"[^\w.\-/ ]", "_", f"{row.label}.{c.column.key}")] = c.value
    with tracker.run(f"report {m.name}", tags, {"overrides": " ".join(table.overrides), **OmegaConf.to_container(settings)}) as run_id:
        tracker.log_metrics(run_id, metrics)
        for f in files:
            tracker.client.log_artifact(run_id, str(f))
    return run_id


def publish(table: Table, settings: DictConfig) -> tuple[list[Path], str | None]:
    """Write every format under <out_dir>/<manifest name>/ and, unless report.log=false, log them."""
    files = write_report(table, Path(settings.out_dir) / table.manifest.name)
    return files, log_report(table, files, settings) if settings.log else None


def summary(table: Table, files: list[Path], run_id: str | None) -> str:
    """What the commands print: the Markdown table, then where it went."""
    return markdown(table) + f"\nwrote {', '.join(map(str, files))}" + (f"; logged as run {run_id}" if run_id else "")


def report(manifest_path, args=()) -> tuple[Table, list[Path], str | None]:
    """Build, write and (unless report.log=false) log one manifest's report."""
    settings, run_overrides = split_overrides(args)
    table = build(load_manifest(manifest_path), run_overrides, settings)
    return table, *publish(table, settings)
