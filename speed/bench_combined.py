"""Combined weather: one layered render against the sum of its layers rendered one by one.

For a few combinations of presets (paper and field layers) on the Sintel-size bench scene of
``bench.py`` (1024 x 436, a textured plane with a near block, moving cameras), times
``render_pair(pair, layers)`` (every layer in one pass, per-pixel depth-ordered composite) and
``render_pair(pair, layer)`` for each layer alone, forward (no gradient) and forward + backward
(gradients for offsets, colour and transparency, beta = 30, the attack's), and prints the
combined time, the sum of the layers' times and their ratio. One torch thread, the process's CPU
time (``time.process_time``: other processes on the machine do not count), the median of
``--repeats`` runs, combined and single runs interleaved so that both see the same machine
state. The target: a ratio of at most 1 (a combined render costs no more than its layers).

    python speed/bench_combined.py [--repeats 5] [--combinations snow+fog rain-heavy+fog-light]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
COMBINATIONS = ("snow+fog", "rain+fog", "snow-moderate+fog-light", "rain-heavy+fog-light",
                "sparks-moderate+fog-moderate")
FRAME_RATE = 24.0


def scene():
    sys.path.insert(0, str(REPO / "tests"))
    from engine_scenes import bench_scene

    pair = bench_scene()
    return pair


def cpu_seconds(fn) -> float:
    start = time.process_time()
    fn()
    return time.process_time() - start


def forward(pair, particles):
    import torch

    from weathergen.engine import render_pair

    with torch.no_grad():
        render_pair(pair, particles)


def backward(pair, particles):
    from weathergen.engine import BETA_ATTACK, LayeredParticles, render_pair

    layers = particles.layers if isinstance(particles, LayeredParticles) else (particles,)
    freed = tuple(r.replace(offset1=r.offset1.clone().requires_grad_(),
                            offset2=r.offset2.clone().requires_grad_(),
                            color=r.color.clone().requires_grad_(),
                            transparency=r.transparency.clone().requires_grad_()) for r in layers)
    record = (LayeredParticles(freed, particles.names) if isinstance(particles, LayeredParticles)
              else freed[0])
    out = render_pair(pair, record, beta=BETA_ATTACK)
    loss = out.image1.sum() + out.image2.sum()
    if loss.requires_grad:          # (a layer that is an atmosphere alone frees nothing here)
        loss.backward()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--combinations", nargs="+", default=list(COMBINATIONS))
    args = parser.parse_args()

    import torch

    from weathergen.engine import load_preset, sample_weather

    torch.set_num_threads(1)
    pair = scene()
    print("Combined weather vs the sum of its layers, 1024x436 bench scene, CPU seconds "
          f"(1 thread, median of {args.repeats})")
    print(f"{'combination':30s} {'particles':>16s} {'pass':>17s} {'combined':>9s} "
          f"{'layers':>9s} {'ratio':>6s}")
    worst = 0.0
    for name in args.combinations:
        layered = sample_weather(pair, load_preset(name), 0, frame_rate=FRAME_RATE)
        counts = "+".join(str(c) for c in layered.counts)
        for label, run in (("forward", forward), ("forward+backward", backward)):
            run(pair, layered)                            # warm-up: templates, atlases
            for record in layered.layers:
                run(pair, record)
            combined, single = [], []
            for _ in range(args.repeats):
                combined.append(cpu_seconds(lambda: run(pair, layered)))
                single.append(sum(cpu_seconds(lambda r=r: run(pair, r)) for r in layered.layers))
            c, s = statistics.median(combined), statistics.median(single)
            worst = max(worst, c / s)
            print(f"{name:30s} {counts:>16s} {label:>17s} {c:9.3f} {s:9.3f} {c / s:6.2f}")
    print(f"largest ratio combined / sum of layers: {worst:.2f} (target: at most 1)")


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
