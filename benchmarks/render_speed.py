"""Speed of the pictures every run logs: seconds per render and per PNG, and per run's worth.

    python benchmarks/render_speed.py                    # a 20,480-face icosphere, 5 repeats
    python benchmarks/render_speed.py --subdivisions 6 --repeats 3

The mesh is trimesh's icosphere (no download), labelled by octant so that every face has one of
8 labels. Prints the median wall-clock seconds of `render_labels` (one 320-px view),
`label_comparison_png` (two views, legend, PNG) and `confusion_png`.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import trimesh

from meshseg.render import confusion_png, label_comparison_png, render_labels


def median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subdivisions", type=int, default=5, help="icosphere subdivisions (5: 20,480 faces)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    sphere = trimesh.creation.icosphere(subdivisions=args.subdivisions)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    centres = v[f].mean(axis=1)
    gt = (centres > 0).astype(int) @ [1, 2, 4]  # octant: 8 labels
    pred = np.where(centres[:, 2] > 0.9, 0, gt)  # a wrong cap, so the two panels differ
    names = [f"part {i}" for i in range(8)]
    confusion = np.bincount(gt * 8 + pred, minlength=64).reshape(8, 8)
    render_labels(v, f, gt, 8)  # warm-up (imports, caches)
    out = {
        "faces": len(f),
        "repeats": args.repeats,
        "render_labels_s": median_seconds(lambda: render_labels(v, f, gt, 8), args.repeats),
        "label_comparison_png_s": median_seconds(lambda: label_comparison_png(v, f, pred, gt, names), args.repeats),
        "confusion_png_s": median_seconds(lambda: confusion_png(confusion, names), args.repeats),
    }
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
