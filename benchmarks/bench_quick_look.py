"""The README's "quick look" attack, timed: one demo pair, RAFT-small, 20 steps.

Runs the command exactly as the README gives it (in a temporary folder) and prints its wall time,
the process's CPU time, and the mean AEE(f, f̌) of random and of adversarial weather from its
``summary.json``. The README promises under a minute on 2 CPU cores and an adversarial AEE
several times the random one.

    python benchmarks/bench_quick_look.py
    python benchmarks/bench_quick_look.py --checkpoint raft-small --device cuda
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: The README's quick look, less the checkpoint and the output folder.
QUICK_LOOK = ["attack", "--model", "raft-small", "--scenes", "street", "--frames-per-scene", "1",
              "--steps", "20", "--lr", "1e-2"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="raft-small", help="RAFT-small weights: a path or the name")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    exe = shutil.which("weathergen") or str(Path(sys.executable).parent / "weathergen")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "quick"
        command = [exe, *QUICK_LOOK, "--checkpoint", args.checkpoint, "--device", args.device,
                   "--out", str(out), "-q"]
        t0 = time.perf_counter()
        subprocess.run(command, check=True)
        wall = time.perf_counter() - t0
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        summary = json.loads((out / "summary.json").read_text())
    print(f"weathergen {' '.join(QUICK_LOOK)} (device {args.device})")
    print(f"  wall {wall:.1f} s, CPU {usage.ru_utime + usage.ru_stime:.1f} s")
    print(f"  AEE(f, f̌): random weather {summary['aee_random']:.3f} px, "
          f"adversarial {summary['aee_adversarial']:.3f} px "
          f"({summary['aee_adversarial'] / summary['aee_random']:.1f}x)")


if __name__ == "__main__":
    main()
