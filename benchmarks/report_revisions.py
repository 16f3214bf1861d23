"""A whole report command timed at two revisions of meshseg on one store, interleaved, with their outputs compared:
what a change to the report's reading costs or saves, end to end.

    git worktree add --detach ../before <rev>
    python benchmarks/report_revisions.py ../before . experiments/claims.yaml --store mlruns --repeats 1

Each checkout runs `python -m meshseg.report <manifest> paths.mlflow_dir=<store>` in its own folder, writing to a
scratch folder; the store should hold the table's runs already (a first report imports them), so that both
revisions read the same store. Prints each run's seconds, the medians and their ratio, and whether the written
files are byte for byte the same.
"""

from __future__ import annotations

import argparse
import filecmp
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def timed_report(checkout: Path, manifest: str, store: Path, out: Path) -> float:
    t = time.perf_counter()
    cmd = [sys.executable, "-m", "meshseg.report", manifest, f"paths.mlflow_dir={store}", f"report.out_dir={out}"]
    subprocess.run(cmd, cwd=checkout, check=True, capture_output=True)
    return time.perf_counter() - t


def same_files(a: Path, b: Path) -> bool:
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    return files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file()) and all(
        filecmp.cmp(a / f, b / f, shallow=False) for f in files
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path, help="a checkout of the revision before")
    ap.add_argument("after", type=Path, help="a checkout of the revision after")
    ap.add_argument("manifest", help="the manifest, relative to each checkout")
    ap.add_argument("--store", type=Path, default=Path("mlruns"), help="the MLflow store both read")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    store = args.store.resolve()
    seconds: dict[str, list[float]] = {"before": [], "after": []}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.repeats):
            for name in ("before", "after"):
                out = Path(tmp) / f"{name}{i}"
                seconds[name].append(timed_report(getattr(args, name).resolve(), args.manifest, store, out))
                print(f"{name}: {seconds[name][-1]:.1f} s", flush=True)
        same = same_files(Path(tmp) / "before0", Path(tmp) / "after0")
    b, a = statistics.median(seconds["before"]), statistics.median(seconds["after"])
    print(f"median before {b:.1f} s, after {a:.1f} s: after/before {a / b:.2f}; outputs the same: {same}")


if __name__ == "__main__":
    main()
