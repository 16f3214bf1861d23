"""A report's table built from its app config, written in every format and logged as an MLflow run."""

from __future__ import annotations

import hashlib
import logging
import re
from dataclasses import replace
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from meshseg.config import run_config
from meshseg.errors import ConfigError
from meshseg.report.aggregate import Bootstrap
from meshseg.report.cells import Table
from meshseg.report.config import run_overrides
from meshseg.report.manifest import Manifest
from meshseg.report.table import check_request, checked_run_config, collect, fold_hashes
from meshseg.report.write import markdown, write_report

log = logging.getLogger("meshseg.report")


def import_results(manifests: list[Manifest], cfg: DictConfig, sets=None, overrides=None) -> None:
    """The shipped records under `report.results` (`results/<dataset>/...`) of the fold runs the manifests'
    tables want (of their `sets`; None: all; with the run `overrides`, None: the app config's), imported into
    the runs' store (idempotent: records already there are skipped), so that a fresh clone reports from
    `results/` with no training. Only those: a table of one study imports its few hundred records, not every
    record of the dataset. Several tables' records go in one import a dataset: one search of the store and one
    read of results/ however many tables (the claims report's)."""
    from meshseg.results import import_records
    from meshseg.tracking import Tracker

    overrides = run_overrides(cfg) if overrides is None else list(overrides)
    root = cfg.report.get("results")
    if not root or not Path(root).is_dir():
        return
    try:  # every cell's run config, before a store is opened: one that does not compose, or that no run could
        configs = [  # start with (branches=7), opens none and imports nothing
            checked_run_config([*m.cell_overrides(g, c), *overrides])
            for m in manifests
            for g in m.groups
            for c in m.columns
            if c.predictions is None
        ]
    except ConfigError:
        return  # the table's own composition names the override at fault
    if not configs:
        return
    datasets = {c.dataset._target_.rsplit(".", 1)[1].lower() for c in configs}  # PSB -> psb
    hashes = set().union(*(fold_hashes(m, overrides, sets) for m in manifests))
    t = configs[0].tracking
    tracker = Tracker(t.uri, t.experiment, t.artifact_dir)
    for name in sorted(datasets):
        if (Path(root) / name).is_dir():
            rep = import_records(tracker, Path(root) / name, hashes)
            if rep.imported or rep.refused:
                log.info("results from %s/%s: %s", root, name, rep.summary())
            for path, why in rep.refused:
                log.warning("not imported: %s: %s", path, why)


def build(manifest: Manifest, cfg: DictConfig) -> Table:
    """The manifest's table from the runs, with the app config's run overrides and `report.*` settings."""
    s = cfg.report
    manifest, sets, paired = requested(manifest, s)
    import_results([manifest], cfg, sets)
    table = collect(manifest, run_overrides(cfg), metric=s.metric, sets=sets, paired=paired, boot=bootstrap(s))
    # the settings that decide which runs a table lacks go into its `meshseg.reproduce` command
    settings = ()
    if s.get("columns") is not None:
        settings += (f"report.columns=[{','.join(c.key for c in manifest.columns)}]",)
    if s.get("results", "results") != "results":
        settings += (f"report.results={'null' if s.results is None else s.results}",)
    table = replace(table, settings=table.settings + settings)
    if s.get("boundaries"):
        from meshseg.report.boundaries import where_errors_lie

        table = replace(table, boundaries=where_errors_lie(table, run_overrides(cfg)))
    return table


def requested(manifest: Manifest, s: DictConfig) -> tuple[Manifest, list | None, list | None]:
    """What `report.*` (`s`) asks of the manifest, checked against it: the manifest with only report.columns,
    report.sets and report.paired (None: the manifest's own). A mistyped setting opens no store."""
    if s.get("columns") is not None:
        manifest = manifest.only_columns([str(k) for k in s.columns])
    sets = None if s.sets is None else list(s.sets)
    paired = None if s.get("paired") is None else OmegaConf.to_container(s.paired)  # replaces the manifest's
    check_request(manifest, s.metric, sets, paired)
    return manifest, sets, paired


def bootstrap(settings: DictConfig) -> Bootstrap:
    """The intervals' settings of `report.*` (n_boot, level, seed)."""
    return Bootstrap(int(settings.n_boot), float(settings.level), int(settings.seed))


def summary_metrics(rows) -> dict[str, float]:
    """What a logged report's run records as metrics: how many cells are ok, incomplete and unavailable, and
    each average's value as `<row label>.<column key>` (`<group>.<row label>.<column key>` where two average
    rows share a label, as Table 3's do, so neither overwrites the other)."""
    cells = [c for r in rows for c in r.cells if c.status != "published"]
    metrics = {
        f"cells_{status}": sum(c.status == status for c in cells) for status in ("ok", "incomplete", "unavailable")
    }
    summaries = [row for row in rows if row.kind != "set"]
    labels = [row.label for row in summaries]
    for row in summaries:
        name = row.label if labels.count(row.label) == 1 else f"{row.group}.{row.label}"
        for c in row.cells:
            if c.value is not None:
                metrics[re.sub(r"[^\w.\-/ ]", "_", f"{name}.{c.column.key}")] = c.value
    return metrics


def log_report(table: Table, files: list[Path], settings: DictConfig) -> str:
    """Log the report as a run of experiment `settings.experiment` in the runs' store: its files as
    artifacts, each complete average as a metric. Returns the run id."""
    from meshseg.tracking import Tracker, git_sha

    m = table.manifest
    settings = OmegaConf.masked_copy(settings, [k for k in settings if k != "dry_run"])  # reproduce's own switch
    cfg = run_config([*m.overrides, *table.overrides])
    tracker = Tracker(cfg.tracking.uri, settings.experiment, cfg.tracking.artifact_dir)
    ident = hashlib.sha256(repr((m.name, table.overrides, OmegaConf.to_yaml(settings))).encode()).hexdigest()[:16]
    tags = {
        "report": m.name,
        "budget": ",".join(table.budgets),
        "config_hash": ident,
        "git_sha": git_sha(),
        "manifest": str(m.path),
    }
    metrics = summary_metrics(table.rows)
    params = {"overrides": " ".join(table.overrides), **OmegaConf.to_container(settings)}
    with tracker.run(f"report {m.name}", tags, params) as run_id:
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
