"""The render core on the Sintel-size bench scene: forward and forward + backward per preset, and
the tensor operations of an attack step's render and of a training batch's weather.

Times ``render_pair`` forward (no gradient) and forward + backward (gradients for both offsets,
colour and transparency, beta = 30) for snow, rain and sparks at 3000 particles and fog at its
preset's count, on the 1024 x 436 scene of ``bench.py``, one torch thread, the process's CPU time,
medians. With ``--before SRC`` (the source tree of an earlier weathergen, e.g.
``git worktree add /tmp/before <commit>``) the same timings run on that code in subprocesses,
alternating with the installed one for ``--rounds`` rounds so that both see the same machine
load, and the ratios are printed (the targets: no slower anywhere, at least 2x faster forward +
backward for snow and sparks).

Then the counts of tensor operations (kernel launches on a GPU; counted here on the CPU, every
dispatched operation, views and host-side bookkeeping included) of the render part of one attack
step (forward + backward of snow on one Sintel-size pair, stamps reused as the attack does, at
3000 and 12000 particles) and of the weather of a training batch of 8 Sintel-size pairs (snow and
rain, a weather field, and a mix of both models), with the CPU's chunk size and with a GPU's
(2**25 elements, views not cut), and the CPU time of the batch both ways: the CPU's small chunks
cost operations in proportion to the work but run faster than one large chunk (their temporaries
stay in the caches), so the count bounded by the work's chunks is the GPU's. The CUDA table is
still to be measured (no GPU was lent when these figures were taken).

    python speed/bench_core.py [--before SRC] [--rounds 3] [--repeats 5]
"""

from __future__ import annotations

import contextlib
import json
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_common  # noqa: E402  (the options, the worker, the earlier tree)
PRESETS = ("snow", "rain", "sparks", "fog")


def measure(repeats: int) -> dict:
    """Median CPU seconds of forward and forward + backward per preset with the importable
    weathergen."""
    import torch

    sys.path.insert(0, str(REPO / "tests"))
    from engine_scenes import bench_scene

    from weathergen.engine import load_preset, sample_particles

    torch.set_num_threads(1)
    pair = bench_scene()
    result = {}
    for name in PRESETS:
        parts = sample_particles(pair, load_preset(name), seed=0)
        forward, forward_backward = bench_common.render_calls(pair, parts)
        for label, fn in (("forward", forward), ("forward_backward", forward_backward)):
            result[f"{name} {label}"] = bench_common.cpu_median(fn, repeats)
    return result


def run_worker(repeats: int, pythonpath: str | None = None) -> dict:
    return bench_common.run_worker(__file__, repeats, pythonpath)


def operation_counts() -> None:
    """Tensor operations of an attack step's render and of a training batch's weather."""
    import torch

    sys.path.insert(0, str(REPO / "tests"))
    from engine_scenes import count_operations, plane_pair, pose, rotation

    from weathergen.engine import (BETA_ATTACK, build_stamps, load_preset, load_templates,
                                   render_pair, sample_weather)
    from weathergen.framepair import FramePairBatch

    count = count_operations

    def seconds(fn) -> float:
        times = []
        for _ in range(3):
            start = time.process_time()
            fn()
            times.append(time.process_time() - start)
        return statistics.median(times)

    torch.set_num_threads(1)

    def sintel(i):
        cam1 = pose(rotation(roll_deg=3, pitch_deg=-5 + i))
        cam2 = pose(rotation(roll_deg=3, pitch_deg=-4 + i, yaw_deg=1), centre=(0.05, 0.0, 0.1))
        pair = plane_pair(436, 1024, depth=6.0, near_block=True, cam1_from_world=cam1,
                          cam2_from_world=cam2, seed=i)
        pair.depth1[..., :, 600:] = 2.0
        pair.depth2[..., :, 600:] = 2.0
        return pair

    print("\ntensor operations (every dispatched operation, counted on the CPU)")
    pair = sintel(0)
    for particles in (3000, 12000):
        parts = sample_weather(pair, load_preset("snow", {"count": particles}), 0)
        stamps = build_stamps([parts], load_templates("flakes"))
        leaves = {k: getattr(parts, k).clone().requires_grad_(True)
                  for k in ("offset1", "offset2", "color", "transparency")}
        moved = parts.replace(**leaves)

        def attack_render():
            out = render_pair(pair, moved, beta=BETA_ATTACK, stamps=stamps)
            (out.image1.sum() + out.image2.sum()).backward()

        def attack_render_gpu_chunks():
            with _gpu_split():      # the backward pass chunks as the forward did
                out = _gpu_chunks(FramePairBatch.stack([pair]), [moved], beta=BETA_ATTACK,
                                  stamps=stamps)
                (out.image1.sum() + out.image2.sum()).backward()

        print(f"  attack step's render (snow, {particles} particles, forward + backward): "
              f"{count(attack_render)} (CPU chunks), {count(attack_render_gpu_chunks)} "
              f"(a GPU's chunks)")
    pairs = [sintel(i) for i in range(8)]
    batch = FramePairBatch.stack(pairs)
    for label, names in (("snow and rain", ["snow", "rain"] * 4),
                         ("snow-light", ["snow-light"] * 8),
                         ("snow, rain, snow-light, rain-light", ["snow", "rain", "snow-light",
                                                                 "rain-light"] * 2)):
        records = [sample_weather(p, load_preset(n), i, frame_rate=24.0)
                   for i, (p, n) in enumerate(zip(pairs, names))]
        cpu = count(lambda: render_pair(batch, records))
        gpu = count(lambda: _gpu_chunks(batch, records))
        cpu_s = seconds(lambda: render_pair(batch, records))
        gpu_s = seconds(lambda: _gpu_chunks(batch, records))
        print(f"  training batch of 8 Sintel-size pairs, {label}: {cpu} (CPU chunks, "
              f"{cpu_s:.2f} s CPU time), {gpu} (a GPU's chunks, {gpu_s:.2f} s on this CPU)")
    print(f"  one dispatched operation on a tiny tensor: {_dispatch_cost() * 1e6:.1f} us CPU time")


def _dispatch_cost() -> float:
    """CPU seconds of one tensor operation whose arithmetic is negligible (what each operation
    of the counts above costs beyond its elements)."""
    import torch

    x = torch.zeros(8)
    start = time.process_time()
    for _ in range(20000):
        x.add_(1.0)
    return (time.process_time() - start) / 20000


@contextlib.contextmanager
def _gpu_split():
    """Views not cut into the CPU's fixed pieces (which keep a view's additions in one order),
    as on a GPU."""
    from weathergen.engine.rendering import splat

    split, splat.PLANE_SPLIT = splat.PLANE_SPLIT, 1 << 40
    try:
        yield
    finally:
        splat.PLANE_SPLIT = split


def _gpu_chunks(batch, records, **options):
    """Render chunked as on a GPU with free memory: 2**25 elements per chunk, views not cut
    (see :func:`_gpu_split`)."""
    from weathergen.engine import render

    with _gpu_split():
        return render(batch.image1, batch.image2, batch.depth1, batch.depth2, batch.intrinsics,
                      batch.cam1_from_world, batch.cam2_from_world, records,
                      chunk_elements=1 << 25, **options)


def main():
    args = bench_common.before_parser(__doc__, rounds=3).parse_args()
    if args.worker:
        print(json.dumps(measure(args.repeats)))
        return
    print(f"render core, 1024x436, one thread, CPU time, medians of {args.repeats}"
          + (f" x {args.rounds} rounds" if args.before else ""))
    if args.before is None:
        now = run_worker(args.repeats)
        for key, value in now.items():
            print(f"  {key:24} {value:.3f} s")
    else:
        before, after = bench_common.before_and_after(__file__, args.before, args.rounds,
                                                      args.repeats)
        print(f"  {'':24} {'before s':>9} {'now s':>9} {'speed-up':>9}")
        for key in before[0]:
            b = bench_common.median_of(before, key)
            a = bench_common.median_of(after, key)
            print(f"  {key:24} {b:9.3f} {a:9.3f} {b / a:8.2f}x")
    operation_counts()


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
