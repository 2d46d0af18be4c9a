"""Command-line options and the one-process-per-measurement runner shared by the attack
benchmarks (bench_attack.py, bench_batch.py).

A script builds its parser in option order: :func:`parser` (``--models``), its own options,
:func:`add_run_options` (``--preset --size --iters --steps``), its own again, then :func:`parse`
adds the internal ``--one`` and parses. :func:`measure_in_new_process` runs the script again
with ``--one`` so that each measurement has its own process (its own peak memory).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from typing import Optional


def parser(doc: str, models: list[str]) -> argparse.ArgumentParser:
    """A parser described by the first line of ``doc``, with ``--models`` (default ``models``)."""
    out = argparse.ArgumentParser(description=doc.splitlines()[0])
    out.add_argument("--models", nargs="+", default=models)
    return out


def add_run_options(p: argparse.ArgumentParser, steps: int) -> None:
    """``--preset``, ``--size``, ``--iters`` and ``--steps`` (default ``steps``)."""
    p.add_argument("--preset", default="snow")
    p.add_argument("--size", default="1024x436", help="WIDTHxHEIGHT")
    p.add_argument("--iters", type=int, default=12)
    p.add_argument("--steps", type=int, default=steps, help="timed steps (the fastest counts)")


def parse(p: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    """Add the internal ``--one`` and parse ``argv``; ``width`` and ``height`` come from
    ``--size``."""
    p.add_argument("--one", help=argparse.SUPPRESS)   # internal: one measurement, as JSON
    args = p.parse_args(argv)
    args.width, args.height = (int(v) for v in args.size.lower().split("x"))
    return args


def measure_in_new_process(script: str, one: str, args: argparse.Namespace,
                           *options: str) -> tuple[Optional[dict], str]:
    """Run ``script --one ONE`` with the run options of ``args`` and ``options`` in a fresh
    process: its measurement (the JSON of its last output line) and "", or None and the last
    line of its error output."""
    cmd = [sys.executable, script, "--one", one, "--preset", args.preset, "--size", args.size,
           "--iters", str(args.iters), "--steps", str(args.steps), *options]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        return None, (done.stderr.strip().splitlines() or ["?"])[-1]
    return json.loads(done.stdout.strip().splitlines()[-1]), ""
