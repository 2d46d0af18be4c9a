"""The README's tour, timed: each of its commands in order, and the quick-look attack's figures.

Runs every ``weathergen`` command of the README's tour as written, in order, in a fresh
temporary folder (so the outputs go where the README says, inside it), and prints each one's
wall time and the CPU time of its process; then the quick look's mean AEE(f, f̌) of random and of
adversarial weather from its ``summary.json`` (one demo pair, RAFT-small, 20 steps). These are
the figures the README and docs/attack.md cite. The commands run with the Python of this script
(``python -m weathergen.cli``), so they measure the weathergen that the other benchmarks import.
With ``--device cuda`` only the quick look runs, on the GPU.

    python speed/bench_quick_look.py
    python speed/bench_quick_look.py --device cuda
"""

from __future__ import annotations

import argparse
import json
import re
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The README's quick look, less its output folder (tests/test_readme.py holds the two together).
QUICK_LOOK = ["attack", "--model", "raft-small", "--checkpoint", "raft-small", "--scenes", "street",
              "--frames-per-scene", "1", "--steps", "20", "--lr", "1e-2"]


def tour_commands(readme: str) -> list[list[str]]:
    """The arguments of each ``weathergen`` command in the tour's bash block of ``readme``."""
    section = readme.split("## A five-minute tour", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    lines = (shlex.split(line, comments=True) for line in block.replace("\\\n", " ").splitlines())
    return [words[1:] for words in lines if words and words[0] == "weathergen"]


def timed(words: list[str], cwd: Path) -> tuple[float, float]:
    """Run ``weathergen WORDS`` in ``cwd``: its wall time and its process's CPU time, seconds."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "weathergen.cli", *words], cwd=cwd, check=True,
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    tour = tour_commands((ROOT / "README.md").read_text())
    if args.device != "cpu":
        out = tour[[w[0] for w in tour].index("attack")]
        tour = [[*QUICK_LOOK, "--device", args.device, *out[out.index("--out"):]]]
    with tempfile.TemporaryDirectory() as tmp:
        print(f"the README's tour, in order in a fresh folder (device {args.device}): "
              "wall and CPU seconds")
        summary = None
        for words in tour:
            wall, cpu = timed(words, Path(tmp))
            print(f"  weathergen {shlex.join(words)}\n      wall {wall:.1f} s, CPU {cpu:.1f} s")
            if words[0] == "attack":
                out = Path(tmp) / words[words.index("--out") + 1]
                summary = json.loads((out / "summary.json").read_text())
    print(f"quick look: AEE(f, f̌): random weather {summary['aee_random']:.3f} px, "
          f"adversarial {summary['aee_adversarial']:.3f} px "
          f"({summary['aee_adversarial'] / summary['aee_random']:.1f}x)")


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
