"""Where a report's time goes when it reads its runs from a store: one search of the store's finished runs,
one run's per-mesh table read where the store keeps it against downloaded (the way before 2026-12-05), and the
whole table assembled (`collect`).

    python benchmarks/report_speed.py                                       # Table 1 (leave-one-out, 1,600 runs)
    python benchmarks/report_speed.py experiments/table2_psb_5fold.yaml --runs 100

The store is the default one (MESHSEG_MLFLOW_DIR, else mlruns/), experiment `meshseg`; import the shipped
records first (`python -m meshseg.report <manifest>` does). Medians over --runs of the manifest's runs.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def seconds(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def download_artifact(client, run, name: str, tmp: str) -> str:
    """The way before: the artifact copied out of the store into `tmp`."""
    return client.download_artifacts(run.info.run_id, name, tmp)


def main() -> None:
    from mlflow import MlflowClient

    from meshseg.report import collect, load_manifest
    from meshseg.report.runs import _artifact, _search_finished
    from meshseg.report.table import fold_hashes
    from meshseg.tracking import FoldRecord, store_uri

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("manifest", nargs="?", default=str(REPO / "experiments/table1_psb_loo.yaml"))
    ap.add_argument("--runs", type=int, default=200, help="runs whose per-mesh table is read both ways")
    args = ap.parse_args()
    manifest = load_manifest(args.manifest)
    uri = store_uri(f"sqlite:///{os.environ.get('MESHSEG_MLFLOW_DIR', 'mlruns')}/mlflow.db")
    t = time.perf_counter()
    by_hash = _search_finished(uri, "meshseg")
    search_s = time.perf_counter() - t
    runs = [by_hash[h] for h in sorted(fold_hashes(manifest)) if h in by_hash][: args.runs]
    if not runs:
        sys.exit(f"error: {uri} holds none of {args.manifest}'s runs: import them first (python -m meshseg.report)")
    client = MlflowClient(tracking_uri=uri)
    in_place, download = [], []
    for run in runs:  # interleaved, so that both ways see the same load
        for way, times in ((_artifact, in_place), (download_artifact, download)):
            with tempfile.TemporaryDirectory() as tmp:
                t = time.perf_counter()
                FoldRecord.read_per_mesh(way(client, run, FoldRecord.PER_MESH, tmp))
                times.append(time.perf_counter() - t)
    out = {
        "manifest": Path(args.manifest).name,
        "store_runs": len(by_hash),
        "search_s": round(search_s, 2),
        "runs_read": len(runs),
        "read_in_place_ms": round(1000 * statistics.median(in_place), 2),
        "read_by_download_ms": round(1000 * statistics.median(download), 2),
        "collect_s": round(seconds(lambda: collect(manifest)), 1),
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
