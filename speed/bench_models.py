"""Time and peak memory of the flow networks: forward, and forward + backward to the input images.

Each measurement runs in a fresh process so that its peak resident memory is its own. Weights are
random (speed and memory do not depend on them), so no checkpoint is needed.

    python speed/bench_models.py          # every network, 1024x436, default iterations
    python speed/bench_models.py --models raft-small spynet --size 512x218 --iters 6
    python speed/bench_models.py --device cuda --repeat 5   # (default: CUDA if any, and CPU)

Prints a Markdown table: seconds, peak resident memory of the process, and the part of that peak
added by the measured call (above the memory of the loaded model and inputs). On CUDA the memory
columns are the peak of allocated GPU memory and the part added by the call, and the time is the
median of ``--repeat`` calls after one warm-up call. ``--iters`` only affects recurrent networks
(RAFT, RAFT-small, GMA, FlowFormer; by default each runs its own default: 12, 12, 6, 32); the
others have no iterations.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


#: The order of the tables (networks registered later follow, see :func:`every_network`).
ALL_MODELS = ["raft-small", "raft", "spynet", "spynet-sniklaus", "flownetc", "flownetcrobust",
              "flownet2", "gma", "flowformer"]


def every_network() -> list[str]:
    """Every registered network: those of :data:`ALL_MODELS` in its order, then any other."""
    from weathergen.models import available_models

    registered = available_models()
    return [m for m in ALL_MODELS if m in registered] + [m for m in registered if m not in ALL_MODELS]


def measure(model_name: str, width: int, height: int, iters: int, backward: bool,
            checkpointing: bool, threads: int, device: str = "cpu", repeat: int = 1) -> dict:
    """One measurement in this process (call in a fresh one)."""
    import statistics

    import torch

    from weathergen.models import build_model

    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = build_model(model_name, iters=iters, gradient_checkpointing=checkpointing)
    model.requires_grad_(False).to(device)
    image1 = torch.rand(1, 3, height, width, device=device)
    image2 = torch.rand(1, 3, height, width, device=device)
    cuda = torch.device(device).type == "cuda"

    def once() -> bool:
        if backward:
            a = image1.clone().requires_grad_(True)
            b = image2.clone().requires_grad_(True)
            flow = model(a, b)
            flow.square().mean().backward()  # any scalar loss on the flow
            return bool(torch.isfinite(a.grad).all())
        with torch.no_grad():
            return bool(torch.isfinite(model(image1, image2)).all())

    if cuda:
        once()  # warm-up: kernel selection, allocator
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        before = torch.cuda.memory_allocated()
    else:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux
    times = []
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        ok = once()
        if cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    peak = (torch.cuda.max_memory_allocated() if cuda
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
    return {"seconds": statistics.median(times), "peak_gib": peak / 2**30,
            "added_gib": (peak - before) / 2**30, "finite": ok,
            "threads": torch.get_num_threads(), "iters": getattr(model, "iters", None)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=None,
                        help="networks to measure (default: every registered one)")
    parser.add_argument("--size", default="1024x436", help="WIDTHxHEIGHT")
    parser.add_argument("--iters", type=int, default=None,
                        help="refinement iterations (default: each network's own)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--checkpointing", action="store_true",
                        help="also measure forward + backward with gradient checkpointing")
    parser.add_argument("--device", default="auto",
                        help="cpu, cuda, or auto (default: cuda when available, then cpu)")
    parser.add_argument("--repeat", type=int, default=1,
                        help="timed calls per measurement (median; CUDA adds a warm-up call)")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one measurement
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))

    if args.one:
        name, backward, checkpointing = json.loads(args.one)
        iters = None if args.iters in (None, 0) else args.iters
        print(json.dumps(measure(name, width, height, iters, backward, checkpointing,
                                 args.threads, args.device, args.repeat)))
        return 0

    if args.models is None:
        args.models = every_network()
    devices = [args.device]
    if args.device == "auto":
        import torch

        devices = (["cuda"] if torch.cuda.is_available() else []) + ["cpu"]
    for device in devices:
        table(args, device, width, height)
    return 0


def table(args, device: str, width: int, height: int) -> None:
    """Measure every model on ``device``, each call in a fresh process, and print the table."""
    runs = []
    for name in args.models:
        runs += [(name, False, False), (name, True, False)]
        if args.checkpointing:
            runs.append((name, True, True))
    memory = "peak GPU memory (GiB)" if device != "cpu" else "peak RSS (GiB)"
    iterations = "default" if args.iters is None else args.iters
    print(f"{width}x{height}, {iterations} iterations (recurrent networks), batch 1, "
          f"{device}\n")
    print(f"| model | iterations | pass | seconds | {memory} | added by the pass (GiB) |")
    print("|---|---:|---|---:|---:|---:|")
    for name, backward, checkpointing in runs:
        cmd = [sys.executable, __file__, "--size", args.size, "--iters", str(args.iters or 0),
               "--threads", str(args.threads), "--device", device, "--repeat", str(args.repeat),
               "--one", json.dumps([name, backward, checkpointing])]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        what = "forward + backward" if backward else "forward"
        if checkpointing:
            what += " (gradient checkpointing)"
        flag = "" if r["finite"] else " (non-finite!)"
        print(f"| {name} | {r['iters'] or '-'} | {what} | {r['seconds']:.2f} | "
              f"{r['peak_gib']:.2f} | "
              f"{r['added_gib']:.2f}{flag} |", flush=True)
    print()


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
