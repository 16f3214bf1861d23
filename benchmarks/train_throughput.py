"""Training throughput of the multi-branch 1D CNN against the machine's fp32 matmul peak, in fp32 and bf16-mixed.

    python benchmarks/train_throughput.py                        # CPU, 1 thread, batch 256, 800 features, branches 1-4
    python benchmarks/train_throughput.py --threads 2            # one process with both cores
    python benchmarks/train_throughput.py --batch-size 512 --seconds 5
    python benchmarks/train_throughput.py --features 600 --branches 3
    python benchmarks/train_throughput.py --precisions fp32      # fp32 only (bf16 trains 7-8x slower on an AVX2 CPU)
    python benchmarks/train_throughput.py --device cuda          # the same on a GPU
    python benchmarks/train_throughput.py --malloc-tune          # glibc keeps freed memory (see below)

In one run it measures

* the fp32 matmul peak: median GFLOP/s of repeated large square torch.mm (2048 on CPU, 8192 on CUDA),
  taken before and after the training measurements;
* training samples/s of meshseg.models.cnn1d.MultiBranchCNN1D (the fast model) for each branch count, and
  of the straightforward nn.Conv1d/nn.BatchNorm1d/nn.MaxPool1d network as the paper draws it
  (meshseg.models.cnn1d.PaperCNN1D): one step = forward, cross-entropy, backward, SGD(momentum 0.9) step
  on a random batch; in bf16-mixed as Lightning's `precision="bf16-mixed"` runs it (forward and loss under
  torch.autocast bf16, backward and step outside it, fp32 weights). Each configuration (model, precision) is
  timed for --seconds in --rounds alternating rounds (so background load hits all alike: fp32 and bf16 of one
  branch count back to back, then again), each round in a fresh process after warm-up steps (so none inherits
  another's malloc state, which changes the fast model's speed by 10-20 %), and the median step time over
  its rounds is reported;

(a few minutes with the defaults: bf16 steps are slow where the CPU has no bf16 arithmetic) and prints one
row per branch count: forward MFLOP per sample (flops_per_sample), samples/s, achieved
GFLOP/s (= 3 x forward FLOPs x samples/s: forward, and backward for inputs and weights), % of the matmul
peak, for the fast model and the reference, and the fast model's speed-up, all in fp32; then per branch
count the samples/s in fp32 and bf16-mixed (the range of the rounds' medians in brackets), the bf16/fp32
ratio of the fast model, and the reference in bf16 beside the fast model in bf16.

--threads (default 1, as each of two parallel folds runs with `trainer.threads=1`; 0: torch's default)
sets torch.set_num_threads in every process.

--malloc-tune calls meshseg.training.malloc.tune_glibc_malloc() in the timing processes: glibc's malloc then
keeps freed memory for reuse (mmap threshold 32 MiB, trim threshold 1 GiB) instead of returning it to the
kernel, so the tens of MiB of activations a step allocates are not faulted in and zeroed again every step.
Setting both MALLOC_MMAP_THRESHOLD_=33554432 and MALLOC_TRIM_THRESHOLD_=1073741824 in the environment
before Python starts does the same for any process (e.g. the trainer).
"""

from __future__ import annotations

import argparse
import contextlib
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

PRECISIONS = ("fp32", "bf16")  # bf16: bf16-mixed


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


def training_step(model, x, y, device, bf16: bool = False):
    opt = torch.optim.SGD(model.parameters(), lr=1e-3, momentum=0.9)

    def step() -> float:
        sync(device)
        t = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        with torch.autocast(device.type, torch.bfloat16) if bf16 else contextlib.nullcontext():
            loss = F.cross_entropy(model(x), y)
        loss.backward()
        opt.step()
        sync(device)
        return time.perf_counter() - t

    return step


def worker(args) -> None:
    """Time one configuration in this (fresh) process and print its step times as JSON."""
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.malloc_tune:
        if not tune_glibc_malloc():
            raise SystemExit("--malloc-tune: glibc's mallopt is not available here")
    model_name, b, precision = args.worker[0], int(args.worker[1]), args.worker[2]
    Model = MultiBranchCNN1D if model_name == "fast" else PaperCNN1D
    torch.manual_seed(0)
    model = Model(args.features, args.classes, b).to(device)
    x = torch.randn(args.batch_size, b, args.features, device=device)
    y = torch.randint(0, args.classes, (args.batch_size,), device=device)
    step = training_step(model, x, y, device, bf16=precision == "bf16")
    for _ in range(args.warmup):
        step()
    times, t_end = [], time.perf_counter() + args.seconds / args.rounds
    while time.perf_counter() < t_end or len(times) < args.min_steps:
        times.append(step())
    print(json.dumps(times))


def run_worker(args, model_name: str, branches: int, precision: str) -> list[float]:
    """Step times of one configuration from one fresh worker process (one of --rounds, alternating between
    configurations)."""
    cmd = [sys.executable, __file__, "--worker", model_name, str(branches), precision] + args.passthrough
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
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (CPU; 0: torch's default)")
    p.add_argument("--precisions", nargs="+", choices=PRECISIONS, default=list(PRECISIONS), help="fp32, bf16-mixed")
    p.add_argument("--rounds", type=int, default=3, help="alternating timing rounds per configuration")
    p.add_argument("--matmul-size", type=int, default=None, help="square matmul size (default 2048 CPU, 8192 CUDA)")
    p.add_argument("--no-reference", action="store_true", help="time the fast model only")
    p.add_argument("--malloc-tune", action="store_true", help="keep freed memory in glibc malloc (see docstring)")
    p.add_argument("--worker", nargs=3, metavar=("MODEL", "BRANCHES", "PRECISION"), help=argparse.SUPPRESS)
    p.add_argument("--warmup", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--min-steps", type=int, default=3, help=argparse.SUPPRESS)  # timed steps per round, at least
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
        if k in ("batch_size", "seconds", "features", "classes", "device", "threads", "rounds", "warmup", "min_steps")
        and v is not None
    ] + (["--malloc-tune"] if args.malloc_tune else [])
    if args.threads:
        torch.set_num_threads(args.threads)
    n_mm = args.matmul_size or (8192 if device.type == "cuda" else 2048)
    names = ["fast"] + ([] if args.no_reference else ["reference"])
    configs = [(name, precision) for precision in args.precisions for name in names]  # fast fp32, fast bf16, ...
    configs.sort(key=lambda c: names.index(c[0]))

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
        times = {c: [] for c in configs}
        round_medians = {c: [] for c in configs}
        for _ in range(args.rounds):
            for c in configs:
                ts = run_worker(args, c[0], b, c[1])
                times[c] += ts
                round_medians[c].append(statistics.median(ts))
        medians = {c: statistics.median(ts) for c, ts in times.items()}
        rows.append((b, flops_per_sample(args.features, args.classes, b), medians, round_medians))

    peak_samples += matmul_gflops(device, n_mm)
    peak = statistics.median(peak_samples)
    print(
        f"fp32 matmul peak: {peak:.1f} GFLOP/s (median of {len(peak_samples)} torch.mm {n_mm}x{n_mm}, "
        f"before and after; range {min(peak_samples):.1f}-{max(peak_samples):.1f})"
    )
    print(
        f"training step: forward + cross-entropy + backward + SGD momentum step; GFLOP/s = 3 x forward "
        f"FLOPs x samples/s; median step time over ~{args.seconds:g} s per configuration ({args.rounds} fresh "
        f"process{'es' if args.rounds > 1 else ''}, {args.warmup} warm-up and at least {args.min_steps} "
        "timed steps each)"
    )
    if "fp32" in args.precisions:
        print_fp32(args, names, rows, peak)
    if "bf16" in args.precisions:
        print_bf16(args, configs, rows)


def print_fp32(args, names, rows, peak: float) -> None:
    """samples/s, GFLOP/s and % of the matmul peak of each model in fp32, and the fast model's speed-up."""
    print("fp32:")
    head = f"{'branches':>8} {'fwd MFLOP':>9} | {'fast smp/s':>10} {'GFLOP/s':>8} {'% peak':>6}"
    if len(names) > 1:
        head += f" | {'ref smp/s':>9} {'GFLOP/s':>8} {'% peak':>6} | {'speed-up':>8}"
    print(head)
    print("-" * len(head))
    for b, fwd, medians, _ in rows:
        cells = []
        for name in names:
            sps = args.batch_size / medians[name, "fp32"]
            gflops = 3 * fwd * sps / 1e9
            cells.append(f"{sps:{10 if name == 'fast' else 9}.0f} {gflops:8.1f} {100 * gflops / peak:5.1f}%")
        line = f"{b:>8} {fwd / 1e6:9.2f} | " + " | ".join(cells)
        if len(names) > 1:
            line += f" | {medians['reference', 'fp32'] / medians['fast', 'fp32']:7.2f}x"
        print(line)


def print_bf16(args, configs, rows) -> None:
    """samples/s of every configuration (median, and the range of the rounds' medians), bf16/fp32 of the fast
    model and the reference's bf16 beside the fast model's."""
    print(f"bf16-mixed (samples/s: median [range of the {args.rounds} rounds' medians]):")
    width = 22
    head = f"{'branches':>8} | " + " ".join(f"{name + ' ' + precision:>{width}}" for name, precision in configs)
    both = ("fast", "fp32") in configs
    reference = ("reference", "bf16") in configs
    head += (f" | {'fast bf16/fp32':>14}" if both else "") + (f" | {'ref/fast bf16':>13}" if reference else "")
    print(head)
    print("-" * len(head))
    for b, _, medians, round_medians in rows:
        cells = []
        for c in configs:
            lo, hi = args.batch_size / max(round_medians[c]), args.batch_size / min(round_medians[c])
            cells.append(f"{f'{args.batch_size / medians[c]:.0f} [{lo:.0f}-{hi:.0f}]':>{width}}")
        line = f"{b:>8} | " + " ".join(cells)
        if both:
            line += f" | {medians['fast', 'fp32'] / medians['fast', 'bf16']:13.2f}x"
        if reference:
            line += f" | {medians['fast', 'bf16'] / medians['reference', 'bf16']:12.2f}x"
        print(line)


if __name__ == "__main__":
    main()
