"""Where a 1D CNN training step's time goes, by ablation: the fast model's fp32 step against the same step with
its batch norms, its max-pool + LeakyReLU passes, or both replaced by near-free stand-ins.

    python benchmarks/train_step_parts.py                  # branches 1 and 3, 3 rounds, 1 thread
    python benchmarks/train_step_parts.py --branches 3 --rounds 5

Why not the profiler: on these machines torch.profiler inflates a step by about 1.5x (and 6x with
record_shapes), unevenly across operators, so its shares mislead. Here every variant runs as it does in
training, each round in a fresh process (as benchmarks/train_throughput.py does), variants alternating:

* full    the step of meshseg.models.cnn1d.MultiBranchCNN1D (forward, cross-entropy, backward, SGD step);
* no-bn   batch norm returns its input (no statistics, no normalisation, nothing in the backward);
* no-pool max pool + LeakyReLU become a strided slice z[:, ::2] (same shapes downstream);
* gemm    both: what is left is the convolutions, the fully connected layers and small glue.

It prints the median step time of each, the batch norm's and the pooling's cost (full minus the variant
without it), and the GEMM-only step and the full step as a share of the fp32 matmul peak measured in the
same run (3 x forward FLOPs per sample, as train_throughput.py counts). On an AVX-512 machine torch's
ATEN_CPU_CAPABILITY=avx2 with oneDNN's ONEDNN_MAX_CPU_ISA=AVX2 runs the AVX2 code paths.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import meshseg.models.cnn1d_fast as fast  # noqa: E402
from meshseg.models.cnn1d import flops_per_sample  # noqa: E402
from meshseg.training.malloc import tune_glibc_malloc  # noqa: E402

VARIANTS = ("full", "no-bn", "no-pool", "gemm")


def worker(variant: str, branches: int, args) -> float:
    """Median step seconds of one variant, in this fresh process."""
    torch.set_num_threads(args.threads)
    tune_glibc_malloc()
    if variant in ("no-bn", "gemm"):
        fast.F.batch_norm = lambda z, *_, **__: z  # this process only
    if variant in ("no-pool", "gemm"):
        fast._pool_leaky_relu = lambda z, pool, slope: z[:, ::pool]
    torch.manual_seed(0)
    model = fast.MultiBranchCNN1D(args.features, args.classes, branches)
    opt = torch.optim.SGD(model.parameters(), lr=1e-3, momentum=0.9)
    x = torch.randn(args.batch_size, branches, args.features)
    y = torch.randint(0, args.classes, (args.batch_size,))

    def step() -> float:
        t = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        F.cross_entropy(model(x), y).backward()
        opt.step()
        return time.perf_counter() - t

    for _ in range(3):
        step()
    times, end = [], time.perf_counter() + args.seconds
    while time.perf_counter() < end or len(times) < 3:
        times.append(step())
    return statistics.median(times)


def matmul_peak(n: int = 2048, repeats: int = 10) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    times = []
    for _ in range(repeats + 2):
        t = time.perf_counter()
        torch.mm(a, b)
        times.append(time.perf_counter() - t)
    return 2 * n**3 / statistics.median(times[2:]) / 1e9


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--branches", type=int, nargs="+", default=[1, 3])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--seconds", type=float, default=1.5, help="timed seconds per variant and round")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--features", type=int, default=800)
    p.add_argument("--classes", type=int, default=8)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--worker", nargs=2, metavar=("VARIANT", "BRANCHES"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker[0], int(args.worker[1]), args)))
        return
    torch.set_num_threads(args.threads)
    passthrough = [
        f"--{k.replace('_', '-')}={getattr(args, k)}"
        for k in ("seconds", "batch_size", "features", "classes", "threads")
    ]
    print(
        f"cpu capability {torch.backends.cpu.get_cpu_capability()}, {args.threads} thread(s); batch {args.batch_size}, "
        f"{args.features} features; median step ms over {args.rounds} fresh processes per variant"
    )
    peaks = [matmul_peak()]
    rows = []
    for b in args.branches:
        steps = {v: [] for v in VARIANTS}
        for _ in range(args.rounds):
            for v in VARIANTS:
                cmd = [sys.executable, __file__, "--worker", v, str(b), *passthrough]
                out = subprocess.run(cmd, capture_output=True, text=True)
                if out.returncode:
                    raise SystemExit(f"worker {v} {b} failed:\n{out.stderr}")
                steps[v].append(json.loads(out.stdout.strip().splitlines()[-1]))
        rows.append((b, {v: statistics.median(t) * 1e3 for v, t in steps.items()}))
    peaks.append(matmul_peak())
    peak = statistics.median(peaks)
    print(f"fp32 matmul peak {peak:.1f} GFLOP/s (torch.mm 2048, before and after: {peaks[0]:.1f}, {peaks[1]:.1f})")
    print(
        f"{'branches':>8} {'ideal':>6} | "
        + " ".join(f"{v:>7}" for v in VARIANTS)
        + f" | {'bn':>6} {'pool':>6} | {'gemm %':>6} {'full %':>6}"
    )
    for b, ms in rows:
        ideal = 3 * flops_per_sample(args.features, args.classes, b) * args.batch_size / peak / 1e6  # ms at the peak
        print(
            f"{b:>8} {ideal:6.1f} | "
            + " ".join(f"{ms[v]:7.1f}" for v in VARIANTS)
            + f" | {ms['full'] - ms['no-bn']:6.1f} {ms['full'] - ms['no-pool']:6.1f}"
            + f" | {100 * ideal / ms['gemm']:5.0f}% {100 * ideal / ms['full']:5.0f}%"
        )


if __name__ == "__main__":
    main()
