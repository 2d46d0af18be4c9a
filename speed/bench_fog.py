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

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def measure(repeats: int) -> dict:
    """Median CPU seconds of the fog forward and forward + backward with the importable
    weathergen."""
    import torch

    sys.path.insert(0, str(REPO / "tests"))
    from engine_scenes import bench_scene

    from weathergen.engine import BETA_ATTACK, load_preset, render_pair, sample_particles

    torch.set_num_threads(1)
    pair = bench_scene()
    parts = sample_particles(pair, load_preset("fog"), seed=0)

    def forward():
        with torch.no_grad():
            render_pair(pair, parts)

    def forward_backward():
        leaves = {name: getattr(parts, name).clone().requires_grad_(True)
                  for name in ("offset1", "offset2", "color", "transparency")}
        out = render_pair(pair, parts.replace(**leaves), beta=BETA_ATTACK)
        (out.image1.sum() + out.image2.sum()).backward()

    result = {}
    for name, fn in (("forward", forward), ("forward_backward", forward_backward)):
        fn()
        times = []
        for _ in range(repeats):
            start = time.process_time()
            fn()
            times.append(time.process_time() - start)
        result[name] = statistics.median(times)
    return result


def run_worker(repeats: int, pythonpath: str | None = None, script: str = __file__) -> dict:
    """Run ``script --worker`` in a fresh process (one thread; ``pythonpath``: the weathergen to
    import) and return the JSON it prints last."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if pythonpath is not None:
        env["PYTHONPATH"] = pythonpath
    out = subprocess.run([sys.executable, script, "--worker", "--repeats", str(repeats)],
                         env=env, check=True, capture_output=True, text=True,
                         cwd=tempfile.gettempdir())
    return json.loads(out.stdout.strip().splitlines()[-1])


def staged_copy(src: Path, into: Path) -> Path:
    """The ``weathergen`` package of a source tree, with its presets where the installed package
    keeps them (older trees ship them from the top-level ``presets/`` folder at install)."""
    pkg = into / "weathergen"
    shutil.copytree(src / "weathergen", pkg)
    if not (pkg / "presets").exists() and (src / "presets").is_dir():
        shutil.copytree(src / "presets", pkg / "presets")
        (pkg / "presets" / "__init__.py").touch()
    return into


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", type=Path, help="source tree of an earlier weathergen")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(measure(args.repeats)))
        return
    print(f"fog, 1024x436, one thread, CPU time, medians of {args.repeats}")
    if args.before is None:
        now = run_worker(args.repeats)
        print(f"  forward {now['forward']:.3f} s, forward + backward "
              f"{now['forward_backward']:.3f} s")
        return
    if not (args.before / "weathergen").is_dir():
        sys.exit(f"--before {args.before}: not a weathergen source tree (no weathergen/ folder)")
    with tempfile.TemporaryDirectory() as tmp:
        old_path = str(staged_copy(args.before.resolve(), Path(tmp)))
        before, after = [], []
        for _ in range(args.rounds):
            before.append(run_worker(args.repeats, old_path))
            after.append(run_worker(args.repeats))
    for key in ("forward", "forward_backward"):
        b = statistics.median(r[key] for r in before)
        a = statistics.median(r[key] for r in after)
        print(f"  {key.replace('_', ' + '):18} before {b:.3f} s, now {a:.3f} s: {b / a:.1f}x")


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
