"""Attack throughput against batch size: pair-steps per second of ``attack --batch-size B``.

A step of a batch is what :func:`weathergen.attack.attack_batch` repeats, timed through the same
:class:`~weathergen.attack.BatchOptimisation`: render B pairs' particles, run the network on the
B weather pairs, the summed loss, the backward pass and one Adam update. Each batch size runs in
a fresh process (its own peak memory). Random network weights (they do not change the cost), a
synthetic 1024x436 pair (see bench_attack.py), each pair of the batch with its own particles.

    python speed/bench_batch.py                                   # RAFT-small, CPU, B = 1 2 4
    python speed/bench_batch.py --device cuda --models raft --batch-sizes 1 4 8 --steps 5
"""

from __future__ import annotations

import json
import os
import resource
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import bench_common  # noqa: E402
from bench_attack import synthetic_pair  # noqa: E402


def measure(model_name: str, preset: str, width: int, height: int, iters: int, steps: int,
            batch: int, device: str, count: int | None = None) -> dict:
    """Measure in this process (call in a fresh one); ``count`` particles per pair (None: the
    preset's)."""
    import torch

    from weathergen.attack import AttackSettings, BatchOptimisation
    from weathergen.engine import load_preset, sample_particles
    from weathergen.models import build_model

    torch.manual_seed(0)
    pair = synthetic_pair(width, height)
    overrides = {"count": count} if count else None
    records = [sample_particles(pair, load_preset(preset, overrides), seed=i) for i in range(batch)]
    model = build_model(model_name, iters=iters).to(device)
    model.requires_grad_(False)
    run = BatchOptimisation(model, [pair] * batch, records, AttackSettings(), device=device)
    cuda = device.startswith("cuda")

    def step():
        losses = run.evaluate()[2]
        run.update(losses.sum())
        if cuda:
            torch.cuda.synchronize()

    step()                                           # warm-up (allocator, kernels)
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    memory = (torch.cuda.max_memory_allocated() / 2**30 if cuda
              else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20)
    best = min(times)
    return {"step_seconds": best, "pair_steps_per_second": batch / best, "memory_gib": memory,
            "threads": torch.get_num_threads()}


def main(argv=None) -> int:
    parser = bench_common.parser(__doc__, models=["raft-small"])
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=[1, 2, 4])
    parser.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    bench_common.add_run_options(parser, steps=2)
    args = bench_common.parse(parser, argv)
    width, height = args.width, args.height

    if args.one:
        model_name, batch = args.one.split(":")
        print(json.dumps(measure(model_name, args.preset, width, height, args.iters, args.steps,
                                 int(batch), args.device)))
        return 0

    memory = "peak GPU memory GiB" if args.device.startswith("cuda") else "peak process GiB"
    print(f"Attack throughput ({args.preset}, all four variables) at {width}x{height}, "
          f"{args.iters} iterations, {args.device}:")
    print()
    print(f"| model | batch | step s | pair-steps/s | {memory} |")
    print("|---|---:|---:|---:|---:|")
    for model_name in args.models:
        for batch in args.batch_sizes:
            r, error = bench_common.measure_in_new_process(
                __file__, f"{model_name}:{batch}", args, "--device", args.device)
            if r is None:
                print(f"| {model_name} | {batch} | failed: {error} | | |", flush=True)
                continue
            print(f"| {model_name} | {batch} | {r['step_seconds']:.2f} "
                  f"| {r['pair_steps_per_second']:.3f} | {r['memory_gib']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
