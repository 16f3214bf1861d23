"""`python -m meshseg.reproduce MANIFEST [overrides]`: launch the runs a manifest still lacks, then
write its report.

    python -m meshseg.reproduce experiments/table2_psb_5fold.yaml budget=cpu
    python -m meshseg.reproduce experiments/table2_psb_5fold.yaml budget=cpu report.sets=[Teddy] report.dry_run=true
    python -m meshseg.reproduce experiments/table1_psb_loo.yaml hydra/launcher=joblib   # parallel folds

Every (column, set) with folds missing becomes one `python -m meshseg.run -m` sweep over exactly those
folds (the same Hydra app, sweeper and launcher config as a hand-typed sweep: launcher overrides pass
through). Runs that exist are never launched again; an interrupted reproduce, rerun, does the rest.
Cells no run can fill (a category the dataset lacks) are listed and left alone.
"""

from __future__ import annotations

import logging
import subprocess
import sys

from meshseg.data.mesh import MeshDataError
from meshseg.report import build, load_manifest, publish, split_overrides, summary
from meshseg.report.table import Table

log = logging.getLogger("meshseg.reproduce")


def missing_sweeps(table: Table) -> list[list[str]]:
    """One override list per incomplete (column, set): its overrides, its category, its missing folds."""
    sweeps = []
    for row in table.rows:
        if row.kind != "set":
            continue
        for c in row.cells:
            if c.status == "incomplete":
                sweeps.append([*c.overrides, f"category={c.category}", "fold=" + ",".join(map(str, c.missing))])
    return sweeps


def reproduce(manifest_path, args=()) -> tuple[Table, list[list[str]], list[list[str]], tuple | None]:
    """Launch what is missing (unless report.dry_run), then build, write and log the report.
    Returns the final table, the sweeps launched, those that failed, and (files, report run id)
    or None for a dry run."""
    settings, run_overrides = split_overrides(args)
    manifest = load_manifest(manifest_path)
    table = build(manifest, run_overrides, settings)
    for row in table.rows:
        for c in row.cells:
            if row.kind == "set" and c.status == "unavailable":
                log.warning("cannot run %s / %s: %s", row.label, c.column.key, c.problem)
    sweeps = missing_sweeps(table)
    folds = sum(len(s[-1].split(",")) for s in sweeps)
    log.info("%s: %d cell(s) lack %d fold run(s)", manifest.name, len(sweeps), folds)
    if settings.dry_run:
        for i, over in enumerate(sweeps, 1):
            log.info("[%d/%d] would run: -m meshseg.run -m %s", i, len(sweeps), " ".join(over))
        return table, sweeps, [], None
    failed = []
    for i, over in enumerate(sweeps, 1):
        cmd = [sys.executable, "-m", "meshseg.run", "-m", *over]
        log.info("[%d/%d] %s", i, len(sweeps), " ".join(cmd[1:]))
        if subprocess.run(cmd).returncode != 0:
            failed.append(over)
            log.error("sweep failed (its runs are marked FAILED in the store): %s", " ".join(over))
    if sweeps:
        table = build(manifest, run_overrides, settings)
    return table, sweeps, failed, publish(table, settings)


def main(argv: list[str]) -> int:
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if argv else 2
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        table, _, failed, published = reproduce(argv[0], argv[1:])
    except (MeshDataError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if published:
        print(summary(table, *published))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
