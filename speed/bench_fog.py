"""Fog, the slowest preset to render, against an earlier weathergen on the same scene and machine.

Times the ``fog`` preset (60 billboards up to 451 px on the 1024 x 436 scene of bench.py) forward
and forward + backward (gradients for the offsets, colour and transparency, beta = 30), one torch
thread, the process's CPU time, medians. With ``--before SRC`` (the source tree of an earlier
weathergen, e.g. ``git worktree add /tmp/before <commit>``) the same timing runs on that code in
a subprocess, alternating with the installed one for ``--rounds`` rounds so that both see the same
machine load, and the ratios are printed.

    python speed/bench_fog.py [--before SRC] [--rounds 2] [--repeats 5]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_common  # noqa: E402  (the options, the worker, the earlier tree)

REPO = Path(__file__).resolve().parents[1]


def measure(repeats: int) -> dict:
    """Median CPU seconds of the fog forward and forward + backward with the importable
    weathergen."""
    import torch

    sys.path.insert(0, str(REPO / "tests"))
    from engine_scenes import bench_scene

    from weathergen.engine import load_preset, sample_particles

    torch.set_num_threads(1)
    pair = bench_scene()
    parts = sample_particles(pair, load_preset("fog"), seed=0)
    forward, forward_backward = bench_common.render_calls(pair, parts)
    return {name: bench_common.cpu_median(fn, repeats)
            for name, fn in (("forward", forward), ("forward_backward", forward_backward))}


def main():
    args = bench_common.before_parser(__doc__, rounds=2).parse_args()
    if args.worker:
        print(json.dumps(measure(args.repeats)))
        return
    print(f"fog, 1024x436, one thread, CPU time, medians of {args.repeats}")
    if args.before is None:
        now = bench_common.run_worker(__file__, args.repeats)
        print(f"  forward {now['forward']:.3f} s, forward + backward "
              f"{now['forward_backward']:.3f} s")
        return
    before, after = bench_common.before_and_after(__file__, args.before, args.rounds,
                                                  args.repeats)
    for key in ("forward", "forward_backward"):
        b = bench_common.median_of(before, key)
        a = bench_common.median_of(after, key)
        print(f"  {key.replace('_', ' + '):18} before {b:.3f} s, now {a:.3f} s: {b / a:.1f}x")


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
