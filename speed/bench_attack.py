"""Time and peak memory of one attack step at Sintel resolution: render + network forward + backward.

A step is what :func:`weathergen.attack.attack_pair` repeats, timed through the same
:class:`~weathergen.attack.PairOptimisation`: render the particles with the freed variables, run the
flow network on the weather frames, the loss, the backward pass into the particle variables and one
Adam update. The renderer's own share is measured separately (its forward and
backward with the same particles and a loss on the rendered frames). Each configuration runs in a
fresh process, so its peak resident memory is its own. Network weights are random (speed and memory
do not depend on them); the scene is a synthetic 1024x436 frame pair with a slanted ground plane.

    python speed/bench_attack.py                         # RAFT, 12 iterations, snow
    python speed/bench_attack.py --models raft-small --steps 3 --checkpointing both
"""

from __future__ import annotations

import json
import resource
import sys
import time

import bench_common


def synthetic_pair(width: int, height: int):
    """A frame pair with depth 2..12 scene units (top to bottom: far to near), camera 1 as the
    reference, camera 2 moved 0.05 units to the right; the focal length (1120 px at 1024 wide)
    scales with the width, so that every size sees the same field of view."""
    import torch

    from weathergen.framepair import FramePair, PairId

    g = torch.Generator().manual_seed(0)
    rows = torch.linspace(12.0, 2.0, height).view(1, height, 1).expand(1, height, width)
    f = 1120.0 * width / 1024
    k = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]],
                     dtype=torch.float64)
    move = torch.eye(4, dtype=torch.float64)
    move[0, 3] = -0.05
    return FramePair(id=PairId("bench", "training", "synthetic", 1),
                     image1=torch.rand(3, height, width, generator=g),
                     image2=torch.rand(3, height, width, generator=g),
                     depth1=rows.contiguous(), depth2=rows.contiguous(), intrinsics=k,
                     cam2_from_cam1=move)


def measure(model_name: str, preset: str, width: int, height: int, iters: int, steps: int,
            checkpointing: bool, threads: int) -> dict:
    """Measure in this process (call in a fresh one)."""
    import torch

    from weathergen.attack import AttackSettings, PairOptimisation
    from weathergen.engine import load_preset, sample_particles
    from weathergen.models import build_model

    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(0)
    pair = synthetic_pair(width, height)
    particles = sample_particles(pair, load_preset(preset), seed=0)
    model = build_model(model_name, iters=iters, gradient_checkpointing=checkpointing)
    model.requires_grad_(False)
    # The attack's own per-pair state and step (all four variables, the paper's settings).
    run = PairOptimisation(model, pair, particles, AttackSettings(), device="cpu")

    def render_only():
        out = run.render(run.variables.particles())
        (out.image1.mean() + out.image2.mean()).backward()

    def step():
        loss = run.evaluate()[2]
        run.update(loss)

    render_only()                                   # warm-up (allocator, first-call costs)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        render_only()
        times.append(time.perf_counter() - t0)
    render_seconds = min(times)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    step_times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        step()
        step_times.append(time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    grads_ok = all(bool(torch.isfinite(p.grad).all()) for p in run.variables.parameters())
    return {"step_seconds": min(step_times), "render_seconds": render_seconds,
            "peak_gib": peak / 2**20, "step_added_gib": (peak - before) / 2**20,
            "particles": particles.count, "finite": grads_ok, "threads": torch.get_num_threads()}


def main(argv=None) -> int:
    parser = bench_common.parser(__doc__, models=["raft"])
    bench_common.add_run_options(parser, steps=1)
    parser.add_argument("--checkpointing", choices=("off", "on", "both"), default="off",
                        help="gradient checkpointing in the network")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    args = bench_common.parse(parser, argv)
    width, height = args.width, args.height

    if args.one:
        model_name, ckpt = args.one.split(":")
        print(json.dumps(measure(model_name, args.preset, width, height, args.iters, args.steps,
                                 ckpt == "on", args.threads)))
        return 0

    modes = ["off", "on"] if args.checkpointing == "both" else [args.checkpointing]
    print(f"Attack step ({args.preset}, all four variables) at {width}x{height}, "
          f"{args.iters} iterations, CPU:")
    print()
    print("| model | checkpointing | particles | step s | renderer fwd+bwd s | renderer share "
          "| peak GiB | step adds GiB |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for model_name in args.models:
        for mode in modes:
            r, error = bench_common.measure_in_new_process(
                __file__, f"{model_name}:{mode}", args, "--threads", str(args.threads))
            if r is None:
                print(f"| {model_name} | {mode} | failed: {error} |")
                continue
            share = r["render_seconds"] / r["step_seconds"]
            print(f"| {model_name} | {mode} | {r['particles']} | {r['step_seconds']:.2f} "
                  f"| {r['render_seconds']:.2f} | {100 * share:.0f}% | {r['peak_gib']:.2f} "
                  f"| {r['step_added_gib']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
