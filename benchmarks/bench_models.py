"""Time and peak memory of the flow networks: forward, and forward + backward to the input images.

Each measurement runs in a fresh process so that its peak resident memory is its own. Weights are
random (speed and memory do not depend on them), so no checkpoint is needed.

    python benchmarks/bench_models.py          # RAFT and RAFT-small, 1024x436, 12 iterations
    python benchmarks/bench_models.py --models raft-small --size 512x218 --iters 6

Prints a Markdown table: seconds, peak resident memory of the process, and the part of that peak
added by the measured call (above the memory of the loaded model and inputs).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def measure(model_name: str, width: int, height: int, iters: int, backward: bool,
            checkpointing: bool, threads: int) -> dict:
    """One measurement in this process (call in a fresh one)."""
    import torch

    from weathergen.models import build_model

    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = build_model(model_name, iters=iters, gradient_checkpointing=checkpointing)
    model.requires_grad_(False)
    image1 = torch.rand(1, 3, height, width)
    image2 = torch.rand(1, 3, height, width)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    start = time.perf_counter()
    if backward:
        image1.requires_grad_(True)
        image2.requires_grad_(True)
        flow = model(image1, image2)
        flow.square().mean().backward()  # any scalar loss on the flow
        ok = bool(torch.isfinite(image1.grad).all())
    else:
        with torch.no_grad():
            flow = model(image1, image2)
        ok = bool(torch.isfinite(flow).all())
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {"seconds": seconds, "peak_gib": peak / 2**20, "added_gib": (peak - before) / 2**20,
            "finite": ok, "threads": torch.get_num_threads()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=["raft-small", "raft"])
    parser.add_argument("--size", default="1024x436", help="WIDTHxHEIGHT")
    parser.add_argument("--iters", type=int, default=12)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--checkpointing", action="store_true",
                        help="also measure forward + backward with gradient checkpointing")
    parser.add_argument("--one", help=argparse.SUPPRESS)  # internal: run one measurement
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))

    if args.one:
        name, backward, checkpointing = json.loads(args.one)
        print(json.dumps(measure(name, width, height, args.iters, backward, checkpointing,
                                 args.threads)))
        return 0

    runs = []
    for name in args.models:
        runs += [(name, False, False), (name, True, False)]
        if args.checkpointing:
            runs.append((name, True, True))
    print(f"{width}x{height}, {args.iters} iterations, batch 1, CPU\n")
    print("| model | pass | seconds | peak RSS (GiB) | added by the pass (GiB) |")
    print("|---|---|---:|---:|---:|")
    for name, backward, checkpointing in runs:
        cmd = [sys.executable, __file__, "--size", args.size, "--iters", str(args.iters),
               "--threads", str(args.threads), "--one", json.dumps([name, backward, checkpointing])]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        what = "forward + backward" if backward else "forward"
        if checkpointing:
            what += " (gradient checkpointing)"
        flag = "" if r["finite"] else " (non-finite!)"
        print(f"| {name} | {what} | {r['seconds']:.1f} | {r['peak_gib']:.2f} | "
              f"{r['added_gib']:.2f}{flag} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
