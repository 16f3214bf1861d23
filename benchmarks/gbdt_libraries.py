"""LightGBM against XGBoost for model=gbdt: the same fold's training faces, the same held-out meshes for early
stopping, matched settings; seconds to fit (early stopping, then the refit on every training mesh), seconds to
predict, and the unrefined area-weighted test accuracy.

    python benchmarks/gbdt_libraries.py                                    # L-PSB Vase and Hand, fold 0, budget=trees
    python benchmarks/gbdt_libraries.py --sets Chair --fold 2 branches=1  # any run overrides after the options

Needs both libraries: meshseg installs LightGBM (the one kept); `pip install xgboost-cpu` for the other.
Settings are conf/model/gbdt.yaml's; XGBoost gets their counterparts (hist, lossguide with max_leaves =
num_leaves, colsample_bytree, subsample, reg_lambda, max_bin, min_child_weight from min_child_samples' role).
The feature cache should be warm (`python -m meshseg.features dataset=psb category=Vase`).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from meshseg.metrics import area_weighted_accuracy  # noqa: E402
from meshseg.models.gbdt import GradientBoostedTrees, inner_split  # noqa: E402


def xgboost_fit_predict(s, train, held, tests, threads: int, seed: int) -> tuple[float, float, int, list]:
    """XGBoost with the counterparts of GbdtSettings `s`: (fit seconds, predict seconds, rounds, probabilities)."""
    import xgboost as xgb

    X, (classes, code) = train.X.reshape(len(train.X), -1), np.unique(train.y, return_inverse=True)
    params = {
        "objective": "multi:softprob",
        "num_class": len(classes),
        "eta": s.learning_rate,
        "tree_method": "hist",
        "grow_policy": "lossguide",
        "max_leaves": s.num_leaves,
        "max_depth": 0,
        "min_child_weight": 1e-3 * s.min_child_samples,
        "colsample_bytree": s.feature_fraction,
        "subsample": s.bagging_fraction,
        "reg_lambda": s.lambda_l2,
        "max_bin": s.max_bin,
        "nthread": threads,
        "seed": seed,
        "eval_metric": "mlogloss",
    }
    t0 = time.perf_counter()
    inner = xgb.DMatrix(X[~held], code[~held])
    valid = xgb.DMatrix(X[held], code[held])
    booster = xgb.train(
        params,
        inner,
        s.max_rounds,
        evals=[(valid, "valid")],
        early_stopping_rounds=s.early_stopping_rounds,
        verbose_eval=False,
    )
    rounds = booster.best_iteration + 1
    if s.refit:
        booster = xgb.train(params, xgb.DMatrix(X, code), rounds)
    fit_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    probs = []
    for X_test in tests:
        p = np.zeros((len(X_test), train.n_classes), np.float32)
        p[:, classes] = booster.predict(xgb.DMatrix(X_test.reshape(len(X_test), -1)), iteration_range=(0, rounds))
        probs.append(p)
    return fit_s, time.perf_counter() - t0, rounds, probs


def score(tests, probs) -> float:
    """Mean unrefined area-weighted accuracy over the test meshes."""
    return float(
        np.mean([area_weighted_accuracy(p.argmax(1), m.labels, m.face_areas) for (m, _), p in zip(tests, probs)])
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", nargs="+", default=["Vase", "Hand"])
    ap.add_argument("--fold", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    args, overrides = ap.parse_known_args()

    from meshseg.config import run_config
    from meshseg.data.datasets import build_dataset
    from meshseg.data.splits import build_split
    from meshseg.features.sets import FeatureSet
    from meshseg.models.settings import GbdtSettings
    from meshseg.training.data import FeatureSource, build_train, iter_test_inputs

    print("set | library | fit s | predict s | rounds | test acc (raw, area-weighted)")
    for category in args.sets:
        cfg = run_config(["dataset=psb", "model=gbdt", "budget=trees", f"category={category}", *overrides])
        dataset = build_dataset(cfg.dataset)
        fold = build_split(cfg.split).folds(dataset, category)[args.fold]
        source = FeatureSource(
            dataset,
            category,
            FeatureSet.from_config(cfg.features),
            cfg.paths.cache_dir,
            cfg.branches,
            cfg.ring_adjacency,
            fold,
        )
        train = build_train(source, fold.train, cfg.budget.faces_per_mesh, cfg.seed)
        tests = list(iter_test_inputs(source, fold.test, train.standardiser))
        settings = GbdtSettings.of(dict(cfg.model.trees))
        held = np.isin(train.mesh_index, inner_split(train.mesh_index, settings.inner_meshes, cfg.seed))

        t0 = time.perf_counter()
        model = GradientBoostedTrees(train.n_classes, args.threads, cfg.seed, **dict(cfg.model.trees))
        model.fit(train.X, train.y, train.mesh_index)
        fit_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        probs = [model.predict_proba(X) for _, X in tests]
        pred_s = time.perf_counter() - t0
        print(f"{category} | lightgbm | {fit_s:.1f} | {pred_s:.1f} | {model.rounds_} | {score(tests, probs):.4f}")
        try:
            fit_s, pred_s, rounds, probs = xgboost_fit_predict(
                settings, train, held, [X for _, X in tests], args.threads, cfg.seed
            )
        except ImportError:
            print(f"{category} | xgboost | not installed (pip install xgboost-cpu)")
            continue
        print(f"{category} | xgboost | {fit_s:.1f} | {pred_s:.1f} | {rounds} | {score(tests, probs):.4f}", flush=True)


if __name__ == "__main__":
    main()
