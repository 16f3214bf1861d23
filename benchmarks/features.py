"""Feature speed and memory: faces/s per group and in total, peak memory, on L-PSB meshes.

    python benchmarks/features.py                      # a handful of meshes spanning the sizes
    python benchmarks/features.py --meshes Bust/305 Airplane/61
    python benchmarks/features.py --sample 40          # every 380/40-th mesh by size (a median over L-PSB)

Each mesh runs in a fresh process (so peak memory is that mesh's alone), one after the other,
computing the groups of the chosen set in order without the cache. Time is wall-clock.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

# smallest, quartiles, median and the largest L-PSB mesh (2,682 .. 55,644 faces)
DEFAULT = ["Octopus/125", "Airplane/61", "Human/15", "FourLeg/394", "Chair/117", "Bust/305"]
SET = [
    "curvature",
    "pca",
    "shape_context",
    "agd",
    "sdf",
    "dms",
    "spin_images",
    "cf0",
    "cf_smooth",
    "gc",
    "hks",
    "sihks",
]


def child(root: str, cache_dir: str, mesh: str, groups: list[str]) -> None:
    from meshseg.data.datasets import PSB
    from meshseg.features.registry import get_group

    category, mesh_id = mesh.split("/")
    m = PSB(root, cache_dir).load(category, mesh_id)
    out = {"mesh": mesh, "faces": m.n_faces, "seconds": {}, "peak_mib": {}}
    for name in groups:
        t0 = time.perf_counter()
        X = get_group(name)(m.vertices, m.faces)
        out["seconds"][name] = time.perf_counter() - t0
        out["peak_mib"][name] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        assert X.shape == (m.n_faces, get_group(name).dim)
    print(json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default="../shared/data/psb/LabeledDB_new.tar.xz")
    ap.add_argument("--cache-dir", default=".cache/meshseg")
    ap.add_argument("--meshes", nargs="*", default=None, help="Category/id ...")
    ap.add_argument("--sample", type=int, default=0, help="take N meshes evenly spread over all 380 by face count")
    ap.add_argument("--groups", nargs="*", default=SET)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args.root, args.cache_dir, args.child, args.groups)

    meshes = args.meshes or DEFAULT
    if args.sample:
        from meshseg.data.datasets import PSB
        from meshseg.data.io import read_off

        ds = PSB(args.root, args.cache_dir)
        sized = sorted(
            (len(read_off(ds.root / c / f"{m}.off")[1]), f"{c}/{m}") for c in ds.categories for m in ds.mesh_ids(c)
        )
        step = len(sized) / args.sample
        meshes = [sized[int(i * step)][1] for i in range(args.sample)]

    rows = []
    t_all = time.perf_counter()
    for mesh in meshes:
        r = subprocess.run(
            [
                sys.executable,
                __file__,
                "--root",
                args.root,
                "--cache-dir",
                args.cache_dir,
                "--child",
                mesh,
                "--groups",
                *args.groups,
            ],
            capture_output=True,
            text=True,
        )
        if r.returncode:
            sys.exit(f"{mesh} failed:\n{r.stderr[-3000:]}")
        rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
        tot = sum(rows[-1]["seconds"].values())
        print(
            f"{mesh:>14}: {rows[-1]['faces']:6d} faces, {tot:6.1f} s, {rows[-1]['faces'] / tot:6.0f} faces/s, "
            f"peak {max(rows[-1]['peak_mib'].values()):5.0f} MiB",
            flush=True,
        )

    names = [r["mesh"] for r in rows]
    width = max(10, *(len(n) for n in names))
    print("\nfaces/s per group (wall clock, one process, no cache); last column: median over meshes")
    print(f"{'group':<14}" + "".join(f"{n:>{width + 1}}" for n in names) + f"{'median':>10}")
    print(f"{'faces':<14}" + "".join(f"{r['faces']:>{width + 1}}" for r in rows))
    for g in args.groups:
        rates = [r["faces"] / r["seconds"][g] for r in rows]
        print(f"{g:<14}" + "".join(f"{x:>{width + 1}.0f}" for x in rates) + f"{statistics.median(rates):>10.0f}")
    totals = [r["faces"] / sum(r["seconds"].values()) for r in rows]
    print(f"{'TOTAL':<14}" + "".join(f"{x:>{width + 1}.0f}" for x in totals) + f"{statistics.median(totals):>10.0f}")
    peaks = [max(r["peak_mib"].values()) for r in rows]
    print(f"{'peak MiB':<14}" + "".join(f"{x:>{width + 1}.0f}" for x in peaks) + f"{statistics.median(peaks):>10.0f}")
    print(f"\nbenchmark wall time: {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
