"""Training throughput of the multi-branch 1D CNN against the machine's fp32 matmul peak.

    python benchmarks/train_throughput.py                        # CPU, batch 256, 800 features, branches 1-4
    python benchmarks/train_throughput.py --batch-size 512 --seconds 5
    python benchmarks/train_throughput.py --features 600 --branches 3
    python benchmarks/train_throughput.py --device cuda          # the same on a GPU
    python benchmarks/train_throughput.py --malloc-tune          # glibc keeps freed memory (see below)

In one run it measures

* the fp32 matmul peak: median GFLOP/s of repeated large square torch.mm (2048 on CPU, 8192 on CUDA),
  taken before and after the training measurements;
* training samples/s of meshseg.models.cnn1d.MultiBranchCNN1D (the fast model) for each branch count, and
  of the straightforward nn.Conv1d/nn.BatchNorm1d/nn.MaxPool1d network as the paper draws it
  (meshseg.models.cnn1d.PaperCNN1D): one step = forward, cross-entropy, backward, SGD(momentum 0.9) step
  on a random batch. Each model is timed for --seconds in --rounds alternating rounds (so background load
  hits both alike), each round in a fresh process after warm-up steps (so neither model inherits the
  other's malloc state, which changes the fast model's speed by 10-20 %), and the median step time is
  reported;

(about 2 minutes with the defaults) and prints one row per branch count: forward MFLOP per sample
(flops_per_sample), samples/s, achieved
GFLOP/s (= 3 x forward FLOPs x samples/s: forward, and backward for inputs and weights), % of the matmul
peak, for the fast model and the reference, and the fast model's speed-up.

--malloc-tune calls meshseg.training.malloc.tune_glibc_malloc() in the timing processes: glibc's malloc then
keeps freed memory for reuse (mmap threshold 32 MiB, trim threshold 1 GiB) instead of returning it to the
kernel, so the tens of MiB of activations a step allocates are not faulted in and zeroed again every step.
Setting both MALLOC_MMAP_THRESHOLD_=33554432 and MALLOC_TRIM_THRESHOLD_=1073741824 in the environment
before Python starts does the same for any process (e.g. the trainer).
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

from meshseg.models.cnn1d import MultiBranchCNN1D, PaperCNN1D, flops_per_sample  # noqa: E402
from meshseg.training.malloc import tune_glibc_malloc  # noqa: E402


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def matmul_gflops(device: torch.device, n: int, repeats: int = 10) -> list[float]:
    """GFLOP/s of repeated n x n fp32 torch.mm (2 n^3 FLOPs each)."""
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    out = torch.empty(n, n, device=device)
    for _ in range(3):
        torch.mm(a, b, out=out)
    rates = []
    for _ in range(repeats):
        sync(device)
        t = time.perf_counter()
        torch.mm(a, b, out=out)
        sync(device)
        rates.append(2 * n**3 / (time.perf_counter() - t) / 1e9)
    return rates


def training_step(model, x, y, device):
    opt = torch.optim.SGD(model.parameters(), lr=1e-3, momentum=0.9)

    def step() -> float:
        sync(device)
        t = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        F.cross_entropy(model(x), y).backward()
        opt.step()
        sync(device)
        return time.perf_counter() - t

    return step


def worker(args) -> None:
    """Time one model in this (fresh) process and print its step times as JSON."""
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.malloc_tune:
        if not tune_glibc_malloc():
            raise SystemExit("--malloc-tune: glibc's mallopt is not available here")
    model_name, b = args.worker[0], int(args.worker[1])
    Model = MultiBranchCNN1D if model_name == "fast" else PaperCNN1D
    torch.manual_seed(0)
    model = Model(args.features, args.classes, b).to(device)
    x = torch.randn(args.batch_size, b, args.features, device=device)
    y = torch.randint(0, args.classes, (args.batch_size,), device=device)
    step = training_step(model, x, y, device)
    for _ in range(args.warmup):
        step()
    times, t_end = [], time.perf_counter() + args.seconds / args.rounds
    while time.perf_counter() < t_end or len(times) < 3:
        times.append(step())
    print(json.dumps(times))


def run_worker(args, model_name: str, branches: int) -> list[float]:
    """Step times of one model from one fresh worker process (one of --rounds, alternating between models)."""
    cmd = [sys.executable, __file__, "--worker", model_name, str(branches)] + args.passthrough
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"worker {' '.join(cmd[2:])} failed:\n{proc.stderr}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--seconds", type=float, default=3.0, help="timed seconds per model and branch count")
    p.add_argument("--features", type=int, default=800, help="input length D of each branch")
    p.add_argument("--classes", type=int, default=8)
    p.add_argument("--branches", type=int, nargs="+", default=[1, 2, 3, 4])
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (CPU; default: torch's)")
    p.add_argument("--rounds", type=int, default=3, help="alternating timing rounds per model")
    p.add_argument("--matmul-size", type=int, default=None, help="square matmul size (default 2048 CPU, 8192 CUDA)")
    p.add_argument("--no-reference", action="store_true", help="time the fast model only")
    p.add_argument("--malloc-tune", action="store_true", help="keep freed memory in glibc malloc (see docstring)")
    p.add_argument("--worker", nargs=2, metavar=("MODEL", "BRANCHES"), help=argparse.SUPPRESS)
    p.add_argument("--warmup", type=int, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no CUDA device available")
    if args.warmup is None:
        args.warmup = 10 if device.type == "cuda" else 3
    if args.worker:
        return worker(args)
    args.passthrough = [
        f"--{k.replace('_', '-')}={v}"
        for k, v in vars(args).items()
        if k in ("batch_size", "seconds", "features", "classes", "device", "threads", "rounds", "warmup")
        and v is not None
    ] + (["--malloc-tune"] if args.malloc_tune else [])
    if args.threads:
        torch.set_num_threads(args.threads)
    n_mm = args.matmul_size or (8192 if device.type == "cuda" else 2048)
    names = ["fast"] + ([] if args.no_reference else ["reference"])

    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"cpu, {torch.get_num_threads()} threads"
    print(
        f"device: {where}; torch {torch.__version__}; batch {args.batch_size}, {args.features} features, "
        f"{args.classes} classes{'; malloc-tune' if args.malloc_tune else ''}"
    )
    if device.type == "cuda":
        print(f"TF32: matmul {torch.backends.cuda.matmul.allow_tf32}, cuDNN {torch.backends.cudnn.allow_tf32}")
    peak_samples = matmul_gflops(device, n_mm)

    rows = []
    for b in args.branches:
        times = {name: [] for name in names}
        for _ in range(args.rounds):
            for name in names:
                times[name] += run_worker(args, name, b)
        rows.append(
            (
                b,
                flops_per_sample(args.features, args.classes, b),
                {name: statistics.median(ts) for name, ts in times.items()},
            )
        )

    peak_samples += matmul_gflops(device, n_mm)
    peak = statistics.median(peak_samples)
    print(
        f"fp32 matmul peak: {peak:.1f} GFLOP/s (median of {len(peak_samples)} torch.mm {n_mm}x{n_mm}, "
        f"before and after; range {min(peak_samples):.1f}-{max(peak_samples):.1f})"
    )
    print(
        f"training step: forward + cross-entropy + backward + SGD momentum step; GFLOP/s = 3 x forward "
        f"FLOPs x samples/s; median step time over ~{args.seconds:g} s per model ({args.rounds} fresh "
        f"process{'es' if args.rounds > 1 else ''}, {args.warmup} warm-up steps each)"
    )
    head = f"{'branches':>8} {'fwd MFLOP':>9} | {'fast smp/s':>10} {'GFLOP/s':>8} {'% peak':>6}"
    if len(names) > 1:
        head += f" | {'ref smp/s':>9} {'GFLOP/s':>8} {'% peak':>6} | {'speed-up':>8}"
    print(head)
    print("-" * len(head))
    for b, fwd, medians in rows:
        cells = []
        for name in names:
            sps = args.batch_size / medians[name]
            gflops = 3 * fwd * sps / 1e9
            cells.append(f"{sps:{10 if name == 'fast' else 9}.0f} {gflops:8.1f} {100 * gflops / peak:5.1f}%")
        line = f"{b:>8} {fwd / 1e6:9.2f} | " + " | ".join(cells)
        if len(names) > 1:
            line += f" | {medians['reference'] / medians['fast']:7.2f}x"
        print(line)


if __name__ == "__main__":
    main()
