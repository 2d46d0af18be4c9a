"""The README's "quick look" attack, timed: one demo pair, RAFT-small, 20 steps.

Runs the command as the README's tour gives it (into a temporary folder instead of its ``--out``)
and prints its wall time, the process's CPU time, and the mean AEE(f, f̌) of random and of
adversarial weather from its ``summary.json``: the figures the README and docs/attack.md cite.
The command runs with the Python of this script (``python -m weathergen.cli``), so it measures
the weathergen that the other benchmarks import.

    python speed/bench_quick_look.py
    python speed/bench_quick_look.py --device cuda
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: The README's quick look, less its output folder (tests/test_readme.py holds the two together).
QUICK_LOOK = ["attack", "--model", "raft-small", "--checkpoint", "raft-small", "--scenes", "street",
              "--frames-per-scene", "1", "--steps", "20", "--lr", "1e-2"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "quick"
        command = [sys.executable, "-m", "weathergen.cli", *QUICK_LOOK, "--device", args.device,
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
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
