"""The cost of the atmosphere per frame (docs/engine.md, "The atmosphere").

On the Sintel-size bench scene of ``bench.py`` (1024 x 436, f = 1120 px, a camera that moves), for
a uniform atmosphere (``rain-heavy``'s veil: ``τ = β L`` per pixel) and a heterogeneous one
(``fog-moderate``: the banks integrated along coarse rays), the atmosphere alone (its record's
particles left out) is rendered into both frames of the pair; the time is given per frame (half
the pair's). Forward (no gradient) and forward + backward (gradients to the airlight and, for the
heterogeneous one, the density lattice, as the attack takes them; an attack on a uniform medium's
density makes it heterogeneous, at the second row's cost). Then the extra cost of seeing particles through the air:
``rain-heavy`` with its veil against the same drops without it (the drops dimmed one by one).
One torch thread, the process's CPU time (other processes do not count), the median of
``--repeats`` runs; ``--device cuda`` times on a GPU instead (wall clock, synchronised).
``make bench`` runs it and records what it prints in the figures file (docs/figures/bench.md).

    python speed/bench_atmosphere.py [--repeats 5] [--device cpu]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from bench_common import cpu_median, timed  # noqa: E402  (speed/, the script's own folder)


def median(fn, repeats: int, device: str) -> float:
    """Median seconds of ``fn`` after a warm-up (caches, lattices): the process's CPU time on
    the CPU, the synchronised wall clock on a GPU."""
    return cpu_median(fn, repeats) if device == "cpu" else timed(fn, device, repeats)


def records(pair):
    from weathergen.engine import load_preset, sample_weather

    out = {}
    for name in ("rain-heavy", "fog-moderate"):
        record = sample_weather(pair, load_preset(name), 0, frame_rate=24.0)
        out[name] = record
        out[name + " (air alone)"] = record.select(torch.zeros(record.count, dtype=torch.bool))
    out["rain-heavy (no air)"] = out["rain-heavy"].replace(atmosphere=None)
    return out


def forward(pair, record, device):
    from weathergen.engine import render_pair

    def run():
        with torch.no_grad():
            render_pair(pair, record, device=device)
    return run


def backward(pair, record, device):
    """Forward and backward: gradients to the airlight and, for heterogeneous air, to the
    density lattice (a uniform medium keeps its exact, table-free integration)."""
    from weathergen.engine import render_pair

    def run():
        atm = record.atmosphere.to(device)
        changes = {"airlight": atm.airlight.float().clone().requires_grad_()}
        if not atm.uniform:
            changes["density"] = atm.lattice(torch.float32, device).clone().requires_grad_()
        moved = record.to(device).replace(atmosphere=atm.replace(**changes))
        out = render_pair(pair, moved, device=device)
        (out.image1.sum() + out.image2.sum()).backward()
    return run


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    from engine_scenes import bench_scene

    pair = bench_scene()
    recs = records(pair)
    print(f"bench scene {pair.size[1]}x{pair.size[0]}, {args.device}, one thread, medians of "
          f"{args.repeats}; seconds per frame (half a pair)")
    print("| atmosphere | forward | forward + backward |")
    print("|---|---|---|")
    for name, label in (("rain-heavy (air alone)", "uniform (`rain-heavy`'s veil)"),
                        ("fog-moderate (air alone)", "heterogeneous (`fog-moderate`)")):
        f = median(forward(pair, recs[name], args.device), args.repeats, args.device) / 2
        b = median(backward(pair, recs[name], args.device), args.repeats, args.device) / 2
        print(f"| {label} | {f:.4f} | {b:.4f} |")
    with_air = median(forward(pair, recs["rain-heavy"], args.device), args.repeats, args.device)
    without = median(forward(pair, recs["rain-heavy (no air)"], args.device), args.repeats,
                     args.device)
    print(f"rain-heavy ({recs['rain-heavy'].count} drops) forward per frame: {with_air / 2:.4f} s "
          f"with its veil, {without / 2:.4f} s without (the veil and the dimming of the drops: "
          f"{(with_air - without) / 2:+.4f} s)")


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
