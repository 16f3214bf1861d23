"""CPU throughput of the ToG15 2D CNN (meshseg.models.cnn2d) beside the paper's 3-branch 1D CNN.

    python benchmarks/cnn2d_throughput.py                 # torch's default threads
    python benchmarks/cnn2d_throughput.py --threads 1 --repeats 7

Both networks read 600 features (the f600 set) and 8 classes, with the defaults of
conf/model/cnn2d.yaml and conf/model/cnn1d.yaml. For each it measures

* training samples/s at --batch-size (default 256): one step = forward, cross-entropy, backward and an
  SGD(momentum 0.9) step on a fixed random batch, the median of --steps timed steps after warm-up;
* predict faces/s: eval mode, no grad, --faces random faces in batches of --predict-batch (default 256,
  conf/trainer/cpu.yaml's predict_batch_size), as Segmenter.predict_proba runs them.

Each figure is the median over --repeats rounds; the rounds alternate between the models so that
background load hits them alike. Lightning's own per-step overhead (a few ms) is not included: in a
real run (`speed/train_samples_per_s` in MLflow) it dominates for a network this small.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from meshseg.models.cnn1d import MultiBranchCNN1D  # noqa: E402
from meshseg.models.cnn2d import ToG15CNN2D  # noqa: E402
from meshseg.training.malloc import tune_glibc_malloc  # noqa: E402

MODELS = {  # name -> (constructor, branches)
    "cnn2d (ToG15)": (lambda d, c: ToG15CNN2D(d, c), 1),
    "cnn2d, no batch norm": (lambda d, c: ToG15CNN2D(d, c, batch_norm=False), 1),
    "cnn1d 3 branches": (lambda d, c: MultiBranchCNN1D(d, c, 3), 3),
}


def train_rate(net, x, y, steps: int, warmup: int = 3) -> float:
    """Samples/s: the median time of `steps` training steps."""
    net.train()
    opt = torch.optim.SGD(net.parameters(), lr=1e-3, momentum=0.9)
    times = []
    for i in range(warmup + steps):
        t = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        F.cross_entropy(net(x), y).backward()
        opt.step()
        if i >= warmup:
            times.append(time.perf_counter() - t)
    return len(x) / statistics.median(times)


@torch.no_grad()
def predict_rate(net, x, batch: int) -> float:
    """Faces/s of one eval pass over x in batches (after one warm-up batch)."""
    net.eval()
    net(x[:batch])
    t = time.perf_counter()
    for i in range(0, len(x), batch):
        torch.softmax(net(x[i : i + batch]), dim=1)
    return len(x) / (time.perf_counter() - t)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--features", type=int, default=600)
    p.add_argument("--classes", type=int, default=8)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--steps", type=int, default=10, help="timed training steps per round")
    p.add_argument("--faces", type=int, default=8192, help="faces predicted per round")
    p.add_argument("--predict-batch", type=int, default=256)
    p.add_argument("--repeats", type=int, default=5, help="alternating rounds per model")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    p.add_argument("--no-malloc-tune", action="store_true", help="leave glibc malloc as it is (the trainer tunes it)")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if not args.no_malloc_tune:
        tune_glibc_malloc()

    torch.manual_seed(0)
    nets, data = {}, {}
    for name, (make, branches) in MODELS.items():
        nets[name] = make(args.features, args.classes)
        data[name] = (
            torch.randn(args.batch_size, branches, args.features),
            torch.randint(0, args.classes, (args.batch_size,)),
            torch.randn(args.faces, branches, args.features),
        )
    rates = {name: ([], []) for name in MODELS}
    for _ in range(args.repeats):
        for name, net in nets.items():
            x, y, faces = data[name]
            rates[name][0].append(train_rate(net, x, y, args.steps))
            rates[name][1].append(predict_rate(net, faces, args.predict_batch))

    print(
        f"cpu, {torch.get_num_threads()} threads; torch {torch.__version__}; {args.features} features, "
        f"{args.classes} classes; train batch {args.batch_size}, predict batch {args.predict_batch}; "
        f"median of {args.repeats} rounds"
    )
    head = f"{'model':<22} {'params':>9} | {'train smp/s':>11} {'range':>13} | {'predict faces/s':>15} {'range':>15}"
    print(head)
    print("-" * len(head))
    for name, (train, pred) in rates.items():
        n_params = sum(t.numel() for t in nets[name].parameters())
        print(
            f"{name:<22} {n_params:>9,} | {statistics.median(train):>11.0f} {min(train):>6.0f}-{max(train):<6.0f} | "
            f"{statistics.median(pred):>15.0f} {min(pred):>7.0f}-{max(pred):<7.0f}"
        )


if __name__ == "__main__":
    main()
