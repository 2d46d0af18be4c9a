"""What the speed scripts share: their common options, their clocks, the fresh processes they
measure in, the inputs several of them build, and how a GPU figure names its machine.

- **The attack benchmarks' options** (bench_attack.py, bench_batch.py). A script builds its
  parser in option order: :func:`parser` (``--models``), its own options,
  :func:`add_run_options` (``--preset --size --iters --steps``), its own again, then
  :func:`parse` adds the internal ``--one`` and parses. :func:`measure_in_new_process` runs the
  script again with ``--one`` so that each measurement has its own process (its own peak memory).
- **Against an earlier tree** (bench_fog.py, bench_core.py): :func:`before_parser` (``--before
  SRC --rounds --repeats`` and the internal ``--worker``), :func:`run_worker` (the script's
  ``--worker`` in a fresh one-thread process, with the weathergen of a given path) and
  :func:`before_and_after` (both trees, alternating round by round so that both see the same
  machine load; :func:`staged_copy` stages the earlier tree's package).
- **Clocks**: :func:`cpu_median` (the process's CPU time, one thread's figures on a shared CPU),
  :func:`timed` (wall clock on a device, synchronised: bench_tables.py, gpu_session.py).
- **Inputs**: :func:`render_calls` (a render forward, and forward + backward into the particle
  variables), :func:`training_samples` (a training batch of Sintel-size pairs with flow).
- **Records**: :func:`gpu_machine` (the GPU, its memory, torch and CUDA of a GPU figure),
  :func:`write_atomic`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Optional

ROOT = Path(__file__).resolve().parents[1]


# -- the attack benchmarks' options ----------------------------------------------------------------

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


# -- against an earlier tree -----------------------------------------------------------------------

def before_parser(doc: str, rounds: int) -> argparse.ArgumentParser:
    """``--before SRC``, ``--rounds`` (default ``rounds``), ``--repeats`` (default 5) and the
    internal ``--worker`` (measure in this process and print the figures as JSON)."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--before", type=Path, help="source tree of an earlier weathergen")
    p.add_argument("--rounds", type=int, default=rounds)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    return p


def run_worker(script: str, repeats: int, pythonpath: Optional[str] = None) -> dict:
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


def before_and_after(script: str, before: Path, rounds: int,
                     repeats: int) -> tuple[list[dict], list[dict]]:
    """``script``'s worker figures with the weathergen of source tree ``before`` and with the
    importable one, ``rounds`` times each, alternating. Exits with one line when ``before`` is
    not a weathergen source tree."""
    if not (before / "weathergen").is_dir():
        sys.exit(f"--before {before}: not a weathergen source tree (no weathergen/ folder)")
    with tempfile.TemporaryDirectory() as tmp:
        old_path = str(staged_copy(before.resolve(), Path(tmp)))
        earlier, now = [], []
        for _ in range(rounds):
            earlier.append(run_worker(script, repeats, old_path))
            now.append(run_worker(script, repeats))
    return earlier, now


def median_of(results: list[dict], key: str) -> float:
    """The median of ``key`` over the rounds' figures."""
    return statistics.median(r[key] for r in results)


# -- clocks ------------------------------------------------------------------------------------------

def cpu_median(fn: Callable[[], object], repeats: int) -> float:
    """Median CPU seconds of the process over ``repeats`` calls of ``fn``, after one warm-up."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.process_time()
        fn()
        times.append(time.process_time() - start)
    return statistics.median(times)


def sync(device: str) -> None:
    """Wait for the device's queued work (a no-op off CUDA)."""
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], object], device: str, repeats: int) -> float:
    """Median wall-clock seconds of ``repeats`` calls (at least one) after one warm-up call,
    each synchronised with ``device``."""
    fn()
    sync(device)
    times = []
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


# -- inputs -----------------------------------------------------------------------------------------

def render_calls(pair, parts, device=None) -> tuple[Callable[[], None], Callable[[], None]]:
    """``(forward, forward_backward)``: ``render_pair`` of ``parts`` into ``pair`` without
    gradient, and with gradients for both offsets, colour and transparency (beta = 30, the
    attack's) of the sum of both frames. ``device`` None: no device argument (as an earlier
    tree's ``render_pair`` may take none)."""
    import torch

    from weathergen.engine import BETA_ATTACK, render_pair

    on = {} if device is None else {"device": device}

    def forward():
        with torch.no_grad():
            render_pair(pair, parts, **on)

    def forward_backward():
        leaves = {k: getattr(parts, k).clone().requires_grad_(True)
                  for k in ("offset1", "offset2", "color", "transparency")}
        out = render_pair(pair, parts.replace(**leaves), beta=BETA_ATTACK, **on)
        (out.image1.sum() + out.image2.sum()).backward()

    return forward, forward_backward


def training_samples(height: int, width: int, batch: int, wall: bool = False) -> list:
    """``batch`` training samples (:class:`~weathergen.training.PairSample`): plane pairs with a
    near block and cameras that turn a little from pair to pair, random flow (its values do not
    change the cost); ``wall``: the right part (from x = 600 of 1024) at depth 2, as the render
    benchmark's scene."""
    import dataclasses

    import torch

    if str(ROOT / "tests") not in sys.path:
        sys.path.insert(0, str(ROOT / "tests"))
    from engine_scenes import plane_pair, pose, rotation

    from weathergen.framepair import PairId
    from weathergen.training import PairSample

    samples = []
    for i in range(batch):
        cam1 = pose(rotation(roll_deg=3, pitch_deg=-5 + i))
        cam2 = pose(rotation(roll_deg=3, pitch_deg=-4 + i, yaw_deg=1), centre=(0.05, 0.0, 0.1))
        pair = plane_pair(height, width, depth=6.0, near_block=True, cam1_from_world=cam1,
                          cam2_from_world=cam2, seed=i)
        if wall:
            pair.depth1[..., :, width * 600 // 1024:] = 2.0
            pair.depth2[..., :, width * 600 // 1024:] = 2.0
        flow = torch.randn(2, height, width, generator=torch.Generator().manual_seed(i))
        pair = dataclasses.replace(pair, id=PairId("bench", "training", "plane", i + 1),
                                   flow=flow, flow_valid=torch.ones(1, height, width,
                                                                    dtype=torch.bool))
        samples.append(PairSample(pair=pair, index=i, epoch=0))
    return samples


# -- records ----------------------------------------------------------------------------------------

def gpu_machine(device: str) -> dict:
    """What a GPU figure was measured on: torch, Python, host, CPUs and, on CUDA, the GPU's name,
    its memory (GiB) and torch's CUDA version (``gpu`` None off CUDA)."""
    import torch

    info = {"torch": torch.__version__, "python": platform.python_version(),
            "host": platform.node(), "cpus": os.cpu_count()}
    if device.startswith("cuda"):
        props = torch.cuda.get_device_properties(torch.device(device))
        info.update(gpu=props.name, gpu_memory_gib=props.total_memory / 2**30,
                    cuda=torch.version.cuda)
    else:
        info.update(gpu=None)
    return info


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file beside it (no half-written file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
