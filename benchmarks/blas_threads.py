"""Why `trainer.threads` bounds numpy's BLAS pool as well as torch's: PCA & NN's principal axes (one eigh of
the 800 x 800 feature covariance, meshseg.models.pca_nn.principal_axes) timed with BLAS at every core and at
one thread, while busy processes keep each core occupied, as two training workers do.

    python benchmarks/blas_threads.py                      # one busy process per core
    python benchmarks/blas_threads.py --busy 0 --repeats 9 # an idle machine: the extra threads help a little

Each figure is the median over --repeats rounds, the rounds alternating between the two settings so that
background load hits them alike; the spread (min-max) is printed too, since an oversubscribed BLAS pool is
slow by chance: its threads spin waiting for a core the other workers hold.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.interleave import interleaved, print_medians  # noqa: E402
from meshseg.models.pca_nn import principal_axes  # noqa: E402


def _spin(stop) -> None:
    x = 0
    while not stop.is_set():
        x += 1


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--busy", type=int, default=os.cpu_count(), help="busy processes beside (default: one per core)")
    ap.add_argument("--faces", type=int, default=19000, help="training faces (a LOO fold's sample)")
    ap.add_argument("--features", type=int, default=800)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)

    X = np.random.default_rng(0).normal(size=(args.faces, args.features)).astype(np.float32)
    settings = {f"BLAS {os.cpu_count()} threads": os.cpu_count(), "BLAS 1 thread": 1}
    stop = mp.Event()
    procs = [mp.Process(target=_spin, args=(stop,), daemon=True) for _ in range(args.busy)]
    for p in procs:
        p.start()

    def limited(n: int):
        def call():
            with threadpool_limits(limits=n, user_api="blas"):
                principal_axes(X, 50)

        return call

    try:
        times = interleaved({name: limited(n) for name, n in settings.items()}, args.repeats)
    finally:
        stop.set()
        for p in procs:
            p.join()
    print(f"principal_axes of {args.faces} x {args.features}, {args.busy} busy process(es), {os.cpu_count()} cores")
    print_medians(times, "BLAS 1 thread")


if __name__ == "__main__":
    main()
