"""Graph-cut refinement speed: seconds per mesh for refine=graphcut_classic / graphcut_agd.

    python benchmarks/refine_speed.py                  # a ~20k-face synthetic figure, 5 repeats
    python benchmarks/refine_speed.py --faces 60000 --classes 8 --repeats 3

The mesh is a synthetic one (no download) with about --faces faces; the probabilities are its
ground truth blurred with seeded noise (about 70 % argmax accuracy) over --classes labels, so the
cut has real work to do. AGD features are computed once, untimed (they are the run's features).
Prints the median wall-clock seconds of each stage and of the whole `refine_labels` call.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from meshseg.data import synthetic  # noqa: E402
from meshseg.data.mesh import Mesh  # noqa: E402
from meshseg.features.agd import average_geodesic_distance  # noqa: E402
from meshseg.metrics import area_weighted_accuracy  # noqa: E402
from meshseg.refine import graphcut, refine_labels  # noqa: E402

CONF = os.path.join(os.path.dirname(__file__), "..", "conf", "refine")


def median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--faces", type=int, default=20000)
    ap.add_argument("--classes", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    V, F, y = synthetic.generate("figure", 0, min_faces=int(0.9 * args.faces), max_faces=int(1.1 * args.faces))
    mesh = Mesh(V, F, y, tuple(f"part{i}" for i in range(max(args.classes, y.max() + 1))))
    rng = np.random.default_rng(args.seed)
    logits = 1.5 * np.eye(len(mesh.label_names))[y] + rng.normal(size=(len(F), len(mesh.label_names)))
    P = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True)
    agd = average_geodesic_distance(V, F)

    out = {
        "faces": mesh.n_faces,
        "classes": P.shape[1],
        "repeats": args.repeats,
        "median_s": {},
        "acc_raw": area_weighted_accuracy(P.argmax(1), y, mesh.face_areas),
    }
    t, (pairs, angle, length) = median_time(lambda: graphcut.dual_edges(V, F), args.repeats)
    out["median_s"]["dual_edges"] = t
    theta = graphcut.edge_theta(angle)
    w = graphcut.classic_weights(theta, length / length.mean())
    out["median_s"]["alpha_expansion"], _ = median_time(
        lambda: graphcut.alpha_expansion(P, pairs, w, 2.0), args.repeats
    )
    for name in ("graphcut_classic", "graphcut_agd"):
        cfg = OmegaConf.load(os.path.join(CONF, f"{name}.yaml"))
        t, labels = median_time(lambda cfg=cfg: refine_labels(mesh, P, cfg, agd), args.repeats)
        out["median_s"][name] = t
        out[f"acc_{name}"] = area_weighted_accuracy(labels, y, mesh.face_areas)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
