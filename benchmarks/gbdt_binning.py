"""model=gbdt's refit: building the LightGBM Dataset of every training row with fresh bin edges against
reusing the edges of the early-stopping fit (`reference=`), as meshseg.models.gbdt does. A fold's sizes at
budget=trees under 5-fold: 16 training meshes x 4,000 faces, X^1..X^3 of 800 features, 3 of 16 meshes held out.

    python benchmarks/gbdt_binning.py                     # 64,000 x 2,400, one thread
    python benchmarks/gbdt_binning.py --rows 76000 --repeats 5

Random normal inputs (binning cost depends on the sizes, not the values). Each figure is the median over
--repeats rounds, alternating between the two, so that background load hits them alike.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.interleave import interleaved, print_medians  # noqa: E402


def main(argv=None) -> None:
    import lightgbm as lgb

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=64000)
    ap.add_argument("--features", type=int, default=2400)
    ap.add_argument("--held-out", type=float, default=3 / 16, help="share of rows the first fit holds out")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)

    rng = np.random.default_rng(0)
    X = rng.normal(size=(args.rows, args.features)).astype(np.float32)
    y = rng.integers(0, 4, args.rows)
    fit_rows = slice(round(args.held_out * args.rows), None)
    params = {"max_bin": 255, "num_threads": args.threads, "verbosity": -1, "force_row_wise": True}
    first = lgb.Dataset(X[fit_rows], y[fit_rows], params=params, free_raw_data=False).construct()
    builds = {
        "fresh bin edges": lambda: lgb.Dataset(X, y, params=params, free_raw_data=False).construct(),
        "the first fit's edges": lambda: lgb.Dataset(
            X, y, params=params, reference=first, free_raw_data=False
        ).construct(),
    }
    times = interleaved(builds, args.repeats)
    print(f"LightGBM Dataset of {args.rows} x {args.features}, {args.threads} thread(s)")
    print_medians(times, "fresh bin edges")


if __name__ == "__main__":
    main()
