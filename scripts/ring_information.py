"""How much the multi-scale inputs X^2..X^K add to X^1, per L-PSB set (paper §3.4; the budget study's "why").

    python scripts/ring_information.py                                  # the budget study's six sets, K = 4
    python scripts/ring_information.py category=[Vase,Hand] scales=3    # any sets; run-config overrides too

Per mesh, from the cached features (`python -m meshseg.features` computes missing ones), for k = 2..K:
- faces: mean |N^k(u)| over faces u (the faces averaged into X^k(u));
- reach: mean distance from a face's centre to the farthest centre in N^k(u), in % of the mesh's bounding
  box diagonal (the smallest radius of the 2010 features is 1 % of the mesh: curvature's 0.01);
- new: the share of the per-mesh feature variance that X^k - X^1 carries, mean over the feature columns
  (each column standardised over the mesh's faces; 0: X^k repeats X^1, 1: as different as two faces).
Printed as one markdown row per set (means over its meshes), then "new" at k = 3 (the paper's 3B) per feature
group, over all the meshes.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from meshseg.features.rings import neighbourhoods, ring_means  # noqa: E402

STUDY_SETS = ["Vase", "Cup", "Hand", "FourLeg", "Chair", "Airplane"]


def ring_information(V: np.ndarray, F: np.ndarray, X: np.ndarray, scales: int, adjacency: str = "edge") -> list[dict]:
    """[{k, faces, reach, new, columns}] for k = 2..scales (see the module docstring), on one mesh; `columns` is
    "new" per feature column (NaN for a column constant over the mesh)."""
    centres = V[F].mean(axis=1)
    diagonal = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    sd = X.std(axis=0)
    keep = sd > 1e-12 * (1 + np.abs(X).max(axis=0))  # constant columns carry nothing at any scale
    Z = (X[:, keep] - X[:, keep].mean(axis=0)) / sd[keep]
    means = ring_means(Z, F, scales, adjacency)
    out = []
    for k, reach in enumerate(neighbourhoods(F, scales, adjacency), start=2):
        coo = reach.tocoo()
        far = np.zeros(len(F))
        np.maximum.at(far, coo.row, np.linalg.norm(centres[coo.row] - centres[coo.col], axis=1))
        columns = np.full(X.shape[1], np.nan)
        columns[keep] = ((means[k - 1] - Z) ** 2).mean(axis=0)
        faces, reach_pc = float(reach.getnnz(axis=1).mean()), 100 * far.mean() / diagonal
        out.append({"k": k, "faces": faces, "reach": reach_pc, "new": float(np.nanmean(columns)), "columns": columns})
    return out


def main(argv: list[str]) -> None:
    from meshseg.config import run_config
    from meshseg.data.datasets import build_dataset
    from meshseg.features.cache import FeatureCache
    from meshseg.features.sets import FeatureSet

    scales = next((int(a.split("=", 1)[1]) for a in argv if a.startswith("scales=")), 4)
    sets = next((a.split("=", 1)[1].strip("[]").split(",") for a in argv if a.startswith("category=")), STUDY_SETS)
    cfg = run_config(["dataset=psb", *(a for a in argv if not a.startswith(("scales=", "category=")))])
    dataset, fs = build_dataset(cfg.dataset), FeatureSet.from_config(cfg.features)
    cache = FeatureCache(cfg.paths.cache_dir)
    ks, by_column = range(2, scales + 1), []
    print("| set | meshes | faces/mesh | " + " | ".join(f"k={k}: faces, reach %, new" for k in ks) + " |")
    print("|---|---|---|" + "---|" * len(ks))
    for category in sets:
        rows = []
        for mesh_id in dataset.mesh_ids(category):
            m = dataset.load(category, mesh_id)
            X = fs.compute(m.vertices, m.faces, m.content_hash, cache)
            rows.append((m.n_faces, ring_information(m.vertices, m.faces, X, scales, cfg.ring_adjacency)))
        mean = {key: [np.mean([r[k - 2][key] for _, r in rows]) for k in ks] for key in ("faces", "reach", "new")}
        cells = [f"{f:.1f}, {r:.2f}, {n:.3f}" for f, r, n in zip(mean["faces"], mean["reach"], mean["new"])]
        print(f"| {category} | {len(rows)} | {np.mean([n for n, _ in rows]):,.0f} | " + " | ".join(cells) + " |")
        by_column += [r[1]["columns"] for _, r in rows if scales >= 3]
    if by_column:
        with warnings.catch_warnings():  # a column constant on every mesh (AGD's always-zero one) stays NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            per_column = np.nanmean(np.stack(by_column), axis=0)
        print("\n| feature group | columns | new at k=3 |\n|---|---|---|")
        for label, (a, b) in fs.layout.items():
            print(f"| {label} | {b - a} | {np.nanmean(per_column[a:b]):.3f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
