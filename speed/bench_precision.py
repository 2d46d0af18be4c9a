"""Reduced precision against float32, per network, on the demo scene: the flow and a short attack.

For every network and every autocast precision (``--precision bf16``/``fp16``; ``tf32`` needs a
CUDA device and is not measured here) this script runs, on the CPU, on a crop of the bundled demo
scene's first pair:

- the flow, against the float32 flow of the same network: the largest and the RMS end-point
  difference in pixels (and the float32 flow's RMS length, for scale);
- a short weather attack (snow, ``--steps`` Adam steps, the same particles): AEE(f, f̌) of the
  best step in that precision against float32's.

RAFT-small runs with its shipped checkpoint; every other network with random weights (seed 0;
their checkpoints are not shipped), so their figures show the arithmetic's effect on a network
of their architecture, not on the released models. Recurrent networks run ``--iters``
refinement iterations. The last line of the output, ``figures: {...}``, holds every figure as
JSON; a network's flow difference (RMS) beyond its bound (``ModelSpec.precision_bound``) is
flagged in the table, and ``ModelSpec.refused_precisions`` refuses that precision for it.

    python speed/bench_precision.py                     # the paper's six and RAFT-small
    python speed/bench_precision.py --models raft-small gma --steps 3
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))           # the source checkout before an installed copy

#: The precisions measured on the CPU (autocast's).
CPU_PRECISIONS = ("bf16", "fp16")
#: The paper's six networks and RAFT-small (the one whose checkpoint is shipped).
NETWORKS = ("flownet2", "flownetcrobust", "spynet", "raft", "raft-small", "gma", "flowformer")


def demo_pair(width: int, height: int):
    """The demo scene's first pair, its centre cropped to ``width`` x ``height``."""
    from weathergen.datasets import open_dataset
    from weathergen.training.augment import crop_pair

    dataset = open_dataset("demo")
    pair = dataset.load(dataset.pairs()[0])
    h, w = pair.size
    return crop_pair(pair, (h - height) // 2, (w - width) // 2, height, width)


def network(name: str, iters: int):
    """``name`` with its shipped checkpoint (raft-small), else random weights (seed 0); and
    which of the two it is."""
    import torch

    from weathergen.models import build_model, get_model

    if name == "raft-small":
        return get_model(name, iters=iters), "shipped checkpoint"
    torch.manual_seed(0)
    return build_model(name, iters=iters).requires_grad_(False), "random weights"


def flow_difference(model, pair, precision: str) -> dict:
    """The flow in ``precision`` against float32's (pixels)."""
    import torch

    x1, x2 = pair.image1[None], pair.image2[None]
    with torch.no_grad():
        model.precision = "float32"
        reference = model(x1, x2)
        model.precision = precision
        flow = model(x1, x2)
        model.precision = "float32"
    epe = (flow - reference).norm(dim=1)
    return {"max_px": epe.max().item(), "rms_px": epe.pow(2).mean().sqrt().item(),
            "flow_rms_px": reference.norm(dim=1).pow(2).mean().sqrt().item(),
            "finite": bool(torch.isfinite(flow).all())}


def attack_aee(model, pair, particles, precision: str, steps: int) -> float:
    """AEE(f, f̌) of a ``steps``-step snow attack in ``precision`` (pixels)."""
    from weathergen.attack import AttackSettings, attack_pair
    from weathergen.flow import aee

    model.precision = precision
    try:
        result = attack_pair(model, pair, particles, AttackSettings(steps=steps))
    finally:
        model.precision = "float32"
    return aee(result.best_flow, result.benign_flow).item()


def measure(name: str, pair, particles, args) -> dict:
    from weathergen.models import model_spec

    start = time.perf_counter()
    model, weights = network(name, args.iters)
    spec = model_spec(name)
    out = {"weights": weights, "bound_rms_px": spec.precision_bound,
           "aee_float32": attack_aee(model, pair, particles, "float32", args.steps)}
    for precision in args.precisions:
        figures = flow_difference(model, pair, precision)
        figures["aee"] = attack_aee(model, pair, particles, precision, args.steps)
        figures["within_bound"] = figures["finite"] and figures["rms_px"] <= spec.precision_bound
        out[precision] = figures
    out["seconds"] = time.perf_counter() - start
    return out


def table(results: dict, precisions) -> str:
    lines = ["| network | weights | precision | flow vs float32: max / RMS px (flow RMS) "
             "| AEE(f, f̌) float32 | AEE(f, f̌) | difference | bound (RMS px) | within |",
             "|---|---|---|---|---:|---:|---:|---:|---|"]
    for name, r in results.items():
        for p in precisions:
            f = r[p]
            within = "yes" if f["within_bound"] else "**no**"
            lines.append(f"| {name} | {r['weights']} | {p} | {f['max_px']:.4f} / {f['rms_px']:.4f} "
                         f"({f['flow_rms_px']:.2f}) | {r['aee_float32']:.3f} | {f['aee']:.3f} | "
                         f"{f['aee'] - r['aee_float32']:+.4f} | {r['bound_rms_px']:g} | {within} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    import torch

    from weathergen.engine import load_preset, sample_particles
    from weathergen.models import available_models

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(NETWORKS), choices=available_models())
    parser.add_argument("--precisions", nargs="+", default=list(CPU_PRECISIONS),
                        choices=CPU_PRECISIONS)
    parser.add_argument("--size", default="96x64", help="WIDTHxHEIGHT of the demo crop")
    parser.add_argument("--iters", type=int, default=4, help="refinement iterations")
    parser.add_argument("--steps", type=int, default=2, help="attack steps")
    parser.add_argument("--count", type=int, default=300, help="snow particles")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.split("x"))
    torch.set_num_threads(1)
    pair = demo_pair(width, height)
    particles = sample_particles(pair, load_preset("snow", {"count": args.count}), seed=0)
    print(f"Reduced precision against float32 on the CPU (torch {torch.__version__}, 1 thread): "
          f"the demo's first pair cropped to {width}x{height}, {args.iters} refinement "
          f"iterations, a {args.steps}-step snow attack ({particles.count} particles).\n")
    results = {}
    for name in args.models:
        results[name] = measure(name, pair, particles, args)
        print(f"{name}: {results[name]['seconds']:.1f} s", flush=True)
    print("\n" + table(results, args.precisions) + "\n")
    print("figures: " + json.dumps(results, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT / "speed"))
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
