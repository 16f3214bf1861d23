"""Parse speed of the L-PSB: every mesh and its labels, repeated; prints medians.

python benchmarks/load_psb.py [--root ../shared/data/psb/LabeledDB_new.tar.xz] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

from meshseg.data.datasets import PSB
from meshseg.data.io import read_off


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default="../shared/data/psb/LabeledDB_new.tar.xz")
    ap.add_argument("--cache-dir", default=".cache/meshseg")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    t0 = time.perf_counter()
    ds = PSB(args.root, args.cache_dir)
    print(f"resolve root (unpack if first time): {time.perf_counter() - t0:.2f} s")
    paths = [(c, m) for c in ds.categories for m in ds.mesh_ids(c)]
    nbytes = sum((ds.root / c / f"{m}.off").stat().st_size for c, m in paths)

    off_times, full_times = [], []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        faces = sum(len(read_off(ds.root / c / f"{m}.off")[1]) for c, m in paths)
        off_times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        assert sum(ds.load(c, m).n_faces for c, m in paths) == faces
        full_times.append(time.perf_counter() - t0)
    off, full = statistics.median(off_times), statistics.median(full_times)
    print(f"{len(paths)} meshes, {faces} faces, {nbytes / 1e6:.0f} MB of OFF text")
    print(
        f"read_off only      : median {off:6.2f} s  ({faces / off / 1e6:.2f} M faces/s, {nbytes / off / 1e6:.0f} MB/s)"
    )
    print(f"mesh + labels + validation: median {full:6.2f} s  ({faces / full / 1e6:.2f} M faces/s)")


if __name__ == "__main__":
    main()
