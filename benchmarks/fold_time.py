"""Where one fold's time goes: a real `meshseg.run` fold, seconds per phase, and its training rate beside the
bare network's rate measured in the same process.

    python benchmarks/fold_time.py                                   # L-PSB Glasses fold 0, budget=cpu, cnn1d 3B
    python benchmarks/fold_time.py category=Teddy branches=1         # any run overrides
    python benchmarks/fold_time.py model=cnn2d --bare-seconds 5

The feature cache should be warm (`python -m meshseg.features dataset=psb category=Glasses` first): the
phase `features` then only checks it. The fold is run by `meshseg.run.run` on a temporary MLflow store
(nothing is left behind), with the run's own threads and malloc tuning, and its phase timings are read
back from the run's `time/<phase>_s` metrics. The bare network (`--bare-seconds`, before and after the
fold; each the median step, the two averaged) is the run's network on random inputs of the run's batch and input
shape: forward, cross-entropy, backward and the SGD step, nothing else. The ratio of the two rates is
what the training loop costs on top of the kernels. The same for prediction: the network's forward and
softmax alone (eval mode, the run's `trainer.predict_batch_size`) beside the fold's predicted faces/s.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PHASES = ["features", "mesh", "load", "rings", "standardise", "train", "predict", "refine", "log", "pictures"]
DEFAULT = ["dataset=psb", "budget=cpu", "category=Glasses", "fold=0"]


def bare_rate(cfg, n_features: int, n_classes: int, seconds: float) -> tuple[float, int]:
    """Median samples/s of the run's network alone (random inputs, the run's batch size), and the steps timed."""
    import torch
    import torch.nn.functional as F
    from hydra.utils import instantiate

    torch.manual_seed(0)
    net = instantiate(cfg.model.net)(n_features=n_features, n_classes=n_classes, branches=cfg.branches)
    opt = torch.optim.SGD(net.parameters(), lr=1e-3, momentum=0.9)
    batch = int(cfg.budget.batch_size)
    x = torch.randn(batch, cfg.branches, n_features)
    y = torch.randint(0, n_classes, (batch,))
    times, t_end = [], time.perf_counter() + seconds
    for i in range(10**9):
        t = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        F.cross_entropy(net(x), y).backward()
        opt.step()
        if i >= 3:  # warm-up steps are not timed
            times.append(time.perf_counter() - t)
        if time.perf_counter() > t_end and len(times) >= 5:
            break
    return batch / statistics.median(times), len(times)


def bare_forward_rate(cfg, n_features: int, n_classes: int, seconds: float) -> float:
    """Median faces/s of the run's network forward alone (eval mode, no autograd, the run's predict batch)."""
    import torch
    from hydra.utils import instantiate

    torch.manual_seed(0)
    net = instantiate(cfg.model.net)(n_features=n_features, n_classes=n_classes, branches=cfg.branches).eval()
    batch = int(cfg.trainer.predict_batch_size)
    x = torch.randn(batch, cfg.branches, n_features)
    times, t_end = [], time.perf_counter() + seconds
    with torch.no_grad():
        for i in range(10**9):
            t = time.perf_counter()
            torch.softmax(net(x), dim=1)
            if i >= 3:
                times.append(time.perf_counter() - t)
            if time.perf_counter() > t_end and len(times) >= 5:
                break
    return batch / statistics.median(times)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("overrides", nargs="*", help=f"meshseg.run overrides (after the defaults {DEFAULT})")
    p.add_argument("--bare-seconds", type=float, default=10.0, help="seconds of bare-network steps, before and after")
    args = p.parse_args(argv)

    from hydra import compose, initialize_config_dir
    from mlflow import MlflowClient

    from meshseg import CONF_DIR
    from meshseg.run import run, setup_process

    with tempfile.TemporaryDirectory() as tmp:
        overrides = [*DEFAULT, *args.overrides, f"paths.mlflow_dir={tmp}/mlruns", f"paths.log_dir={tmp}/logs"]
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            cfg = compose("run", overrides=overrides)
        setup_process(cfg.trainer)  # the run's threads and malloc tuning, for the bare network too
        from meshseg.data.datasets import build_dataset
        from meshseg.features.sets import FeatureSet

        n_features = FeatureSet.from_config(cfg.features).dim
        n_classes = len(build_dataset(cfg.dataset).label_names(cfg.category))
        is_net = "net" in cfg.model
        bare = (lambda: bare_rate(cfg, n_features, n_classes, args.bare_seconds)) if is_net else (lambda: None)
        forward = (lambda: bare_forward_rate(cfg, n_features, n_classes, args.bare_seconds / 2)) if is_net else bare
        before, forward_before = bare(), forward()
        t0 = time.perf_counter()
        run(cfg)
        wall = time.perf_counter() - t0
        after, forward_after = bare(), forward()

        client = MlflowClient(f"sqlite:///{tmp}/mlruns/mlflow.db")
        (r,) = client.search_runs([client.get_experiment_by_name("meshseg").experiment_id])
        m, n = r.data.metrics, r.data.params

    print(f"fold: {r.info.run_name}  (overrides: {' '.join(overrides[:-2])})")
    print(
        f"{n['n_train_samples']} training samples x {n['n_epochs']} epochs, "
        f"{n['n_test_faces']} test faces, test/acc {m['test/acc']:.4f} (raw {m['test/acc_raw']:.4f})"
    )
    print(f"{'phase':<12} {'seconds':>8}")
    for phase in PHASES:
        if f"time/{phase}_s" in m:
            print(f"{phase:<12} {m[f'time/{phase}_s']:>8.2f}")
    print(f"{'(fold wall)':<12} {wall:>8.2f}")
    print(
        f"training: {m['speed/train_samples_per_s']:.0f} samples/s; "
        f"prediction: {m['speed/predict_faces_per_s']:.0f} faces/s"
    )
    if is_net:
        rates = [before[0], after[0]]
        bare = statistics.mean(rates)
        print(
            f"bare network: {bare:.0f} samples/s (mean of before {before[0]:.0f} and after {after[0]:.0f}; "
            f"{before[1]} + {after[1]} steps); training / bare = {m['speed/train_samples_per_s'] / bare:.2f}"
        )
        fwd = statistics.mean([forward_before, forward_after])
        print(
            f"bare forward: {fwd:.0f} faces/s (before {forward_before:.0f}, after {forward_after:.0f}); "
            f"prediction / bare forward = {m['speed/predict_faces_per_s'] / fwd:.2f}"
        )


if __name__ == "__main__":
    main()
