"""Early stopping (``--early-stop WINDOW:TOL``) on the demo scene: the steps it saves and what it
changes in the reported AEE(f, f̌), against the full step budget.

Each network attacks each demo pair (cropped, on the CPU) with snow for the full ``--steps``
budget. An attack with early stopping runs the same steps as the full one until it ends (the same
seed, the same updates: :func:`weathergen.attack.attack_batch` only leaves out the steps after the
one where the loss has converged), so every setting's stopping step and best step follow from the
full run's per-step loss and distance; the first setting is also run for the first pair and
checked against them. The AEE(f, f̌) compared is the one of the best step's float frames
(``StepRecord.robustness``). RAFT-small runs with its shipped checkpoint, SpyNet with random
weights (seed 0; its checkpoint is not shipped). The last line, ``figures: {...}``, holds every
figure as JSON; ``step_fraction`` of each network with trained weights (the first setting's share
of the full budget's pair-steps) is what ``speed/bench_tables.py --from-figures`` applies to the
weather attacks.

    python speed/bench_early_stop.py
    python speed/bench_early_stop.py --steps 60 --settings 10:0.001 20:0.01
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))           # the source checkout before an installed copy
sys.path.insert(0, str(ROOT / "speed"))

from bench_precision import network  # noqa: E402


def stopped(history, stop) -> tuple[int, int]:
    """``(last step run, best step)`` of an attack with early stopping ``stop`` whose full run
    had ``history``."""
    losses = [r.loss for r in history]
    last = next((k for k in range(len(losses) - 1) if stop.stalled(losses[:k + 1])),
                len(losses) - 1)
    kept = [r.distance for r in history[:last + 1]]
    return last, kept.index(min(kept))


def pairs(count: int, width: int, height: int) -> list:
    from weathergen.datasets import open_dataset
    from weathergen.training.augment import crop_pair

    dataset = open_dataset("demo")
    out = []
    for ref in dataset.pairs()[:count]:
        pair = dataset.load(ref)
        h, w = pair.size
        out.append(crop_pair(pair, (h - height) // 2, (w - width) // 2, height, width))
    return out


def measure(name: str, frames: list, settings: list, args) -> dict:
    """Every pair's full attack, and each setting's steps and AEE derived from it."""
    from weathergen.attack import AttackSettings, attack_pair
    from weathergen.engine import load_preset, sample_particles

    start = time.perf_counter()
    model, weights = network(name, args.iters)
    preset = load_preset("snow", {"count": args.count})
    rows = []
    for i, pair in enumerate(frames):
        particles = sample_particles(pair, preset, seed=i)
        full = attack_pair(model, pair, particles, AttackSettings(steps=args.steps))
        row = {"pair": str(pair.id), "best_step": full.best_step,
               "aee": full.history[full.best_step].robustness, "settings": {}}
        for stop in settings:
            last, best = stopped(full.history, stop)
            row["settings"][str(stop)] = {"steps": last, "best_step": best,
                                          "aee": full.history[best].robustness}
        if i == 0:              # the loop itself, stopping at the derived step
            run = attack_pair(model, pair, particles,
                              AttackSettings(steps=args.steps, early_stop=settings[0]))
            derived = row["settings"][str(settings[0])]
            if (len(run.history) - 1, run.best_step) != (derived["steps"], derived["best_step"]):
                raise RuntimeError(f"{name}: the attack with --early-stop {settings[0]} ran "
                                   f"{len(run.history) - 1} steps (best {run.best_step}), the full "
                                   f"run's history says {derived}")
        rows.append(row)
    return {"weights": weights, "pairs": rows, "seconds": time.perf_counter() - start}


def summary(result: dict, setting: str, budget: int) -> dict:
    """A setting's mean steps run, share of the full budget's pair-steps and AEE change."""
    rows = result["pairs"]
    run = [r["settings"][setting]["steps"] + 1 for r in rows]
    full = sum(r["aee"] for r in rows) / len(rows)
    early = sum(r["settings"][setting]["aee"] for r in rows) / len(rows)
    return {"steps_run": sum(run) / len(run) - 1, "step_fraction": sum(run) / ((budget + 1) * len(run)),
            "aee_full": full, "aee_early": early, "aee_change": early - full}


def main(argv=None) -> int:
    import torch

    from weathergen.attack import EarlyStop

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=["raft-small", "spynet"])
    parser.add_argument("--settings", nargs="+", default=["10:0.001", "20:0.001", "20:0.01"],
                        help="WINDOW:TOL settings; the first gives the figures line")
    parser.add_argument("--steps", type=int, default=60, help="the full budget")
    parser.add_argument("--pairs", type=int, default=2, help="demo pairs")
    parser.add_argument("--size", default="96x64", help="WIDTHxHEIGHT of the demo crops")
    parser.add_argument("--iters", type=int, default=6, help="refinement iterations")
    parser.add_argument("--count", type=int, default=300, help="snow particles")
    args = parser.parse_args(argv)
    settings = [EarlyStop.parse(s) for s in args.settings]
    width, height = (int(v) for v in args.size.split("x"))
    torch.set_num_threads(1)
    frames = pairs(args.pairs, width, height)
    print(f"Early stopping against the full budget of {args.steps} steps: snow "
          f"({args.count} particles), {len(frames)} demo pairs cropped to {width}x{height}, "
          f"{args.iters} refinement iterations, CPU (torch {torch.__version__}, 1 thread).\n")
    print("| network | weights | --early-stop | steps run (mean) | pair-steps, share of the full "
          "budget | AEE(f, f̌) full budget | AEE(f, f̌) early stopping | change |")
    print("|---|---|---|---:|---:|---:|---:|---:|")
    figures = {}
    for name in args.models:
        result = measure(name, frames, settings, args)
        for stop in settings:
            s = summary(result, str(stop), args.steps)
            print(f"| {name} | {result['weights']} | {stop} | {s['steps_run']:.1f} | "
                  f"{s['step_fraction']:.0%} | {s['aee_full']:.3f} | {s['aee_early']:.3f} | "
                  f"{s['aee_change']:+.3f} |", flush=True)
        figures[name] = {**summary(result, str(settings[0]), args.steps), "setting": str(settings[0]),
                         "budget": args.steps, "weights": result["weights"], "pairs": result["pairs"]}
    print("\nfigures: " + json.dumps(figures, sort_keys=True))
    return 0


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
