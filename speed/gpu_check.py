"""Every CUDA test and GPU benchmark in one run, and one table of what came out (`make gpu-check`).

For whoever has an NVIDIA GPU and a CUDA build of torch (`make gpu-check TORCH=torch`). In order:

- the CUDA tests (``pytest -m cuda``: the renderer, the attack step, every network and the training
  augmentation against the CPU, a CUDA render from the command line);
- render: forward and forward + backward of snow, rain, sparks and fog (3000 particles, fog 60)
  on a 1024x436 pair, and a batch of 8 pairs as ``render --device cuda`` renders them;
- field: a weather field over a sequence, sampling and rendering per frame (as ``--sequence``);
- training: the weather of a batch of 6 Sintel-size pairs on the device (``apply_batch``), and a
  RAFT-small and a RAFT training step on the cropped batch;
- attack batch: a step of ``attack --batch-size B`` with RAFT for B = 1, 4, 8;
- tables: the paper's six networks' attack at their best batch size in the paper's precision
  (``bench_tables.py``) and the GPU-hours of the paper's Tables 2-5 that follow;
- networks: forward and forward + backward of every registered network, time and memory.

Prints one Markdown table (seconds: medians after a warm-up call; memory: the peak of allocated
GPU memory during the measurement) and, with ``--json PATH``, writes the figures with the machine
(GPU, torch, CUDA) and the tree (git commit) they were measured on, after each area (a run cut
short keeps the areas it finished), and rewrites the page ``gpu.md`` beside ``PATH`` from it (and
from ``gpu-session.json`` there, if any: :mod:`gpu_figures`); ``make gpu-check`` writes
docs/figures/gpu-check.json and docs/figures/gpu.md. Exits 2 with one line when CUDA is not
there, 1 when a test or a measurement failed, else 0.

    python speed/gpu_check.py [--json docs/figures/gpu-check.json] [--models raft gma]

``--device cpu --quick`` runs every measurement on tiny inputs on the CPU (no tests): a dry run
that the test suite uses to check that the table is assembled; its figures mean nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "tests"))

import bench_common  # noqa: E402  (the training batch, the machine)
import gpu_figures  # noqa: E402  (the page docs/figures/gpu.md)
from figures import tree  # noqa: E402


@dataclass
class Row:
    """One line of the table: ``area`` (tests, render, ...), what was measured, its figures."""

    area: str
    what: str
    seconds: Optional[float] = None
    memory_gib: Optional[float] = None
    note: str = ""
    failed: bool = False


@dataclass(frozen=True)
class Sizes:
    """The sizes of a run: the real ones, or the dry run's tiny ones (``--quick``)."""

    width: int = 1024
    height: int = 436
    count: Optional[int] = None          # particles per preset (None: the preset's)
    fog_count: Optional[int] = None
    frames: int = 25                     # field sequence
    batch: int = 6                       # training batch
    crop: tuple = (368, 768)
    iters: Optional[int] = None          # network iterations (None: each network's default)
    attack_batches: tuple = (1, 4, 8)
    attack_model: str = "raft"
    steps: int = 3                       # timed repeats / attack steps
    train_models: tuple = ("raft-small", "raft")


QUICK = Sizes(width=128, height=64, count=100, fog_count=4, frames=2, batch=2, crop=(48, 96),
              iters=2, attack_batches=(1, 2), attack_model="raft-small", steps=1,
              train_models=("raft-small",))


# -- the device ------------------------------------------------------------------------------------

def cuda_problem(device: str) -> Optional[str]:
    """Why ``device`` cannot run the check (one line), or None."""
    if not device.startswith("cuda"):
        return None
    if not torch.cuda.is_available():
        build = "a CPU-only build" if torch.version.cuda is None else f"built for CUDA {torch.version.cuda}"
        return (f"gpu-check needs a CUDA device, and this torch ({torch.__version__}, {build}) sees "
                f"none; run it on a machine with an NVIDIA GPU, with a CUDA build of torch "
                f"(make gpu-check TORCH=torch)")
    index = torch.device(device).index or 0
    if index >= torch.cuda.device_count():
        return f"gpu-check: {device} is not there ({torch.cuda.device_count()} CUDA device(s))"
    return None


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    return f"CPU, {torch.get_num_threads()} thread(s)"


class Meter:
    """Times a call on ``device`` (median of ``repeats`` after a warm-up) and its peak memory."""

    def __init__(self, device: str, repeats: int):
        self.device, self.repeats = device, max(1, repeats)
        self.cuda = device.startswith("cuda")

    def sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize(self.device)

    def __call__(self, fn: Callable[[], object]) -> tuple[float, Optional[float]]:
        fn()                                # warm-up: kernel selection, the allocator
        self.sync()
        if self.cuda:
            torch.cuda.reset_peak_memory_stats(self.device)
        times = []
        for _ in range(self.repeats):
            start = time.perf_counter()
            fn()
            self.sync()
            times.append(time.perf_counter() - start)
        memory = torch.cuda.max_memory_allocated(self.device) / 2**30 if self.cuda else None
        if self.cuda:
            torch.cuda.empty_cache()
        return statistics.median(times), memory


# -- the measurements -----------------------------------------------------------------------------

def scene(sizes: Sizes):
    """The render benchmark's pair (bench.py): a plane at depth 6 with a near block, moving cameras."""
    from engine_scenes import plane_pair, pose, rotation

    cam1 = pose(rotation(roll_deg=3, pitch_deg=-5))
    cam2 = pose(rotation(roll_deg=3, pitch_deg=-4, yaw_deg=1), centre=(0.05, 0.0, 0.1))
    pair = plane_pair(sizes.height, sizes.width, depth=6.0, near_block=True, cam1_from_world=cam1,
                      cam2_from_world=cam2)
    pair.depth1[..., :, sizes.width * 600 // 1024:] = 2.0
    pair.depth2[..., :, sizes.width * 600 // 1024:] = 2.0
    return pair


def render_rows(device: str, sizes: Sizes) -> list[Row]:
    from weathergen.engine import load_preset, render_pair, sample_particles
    from weathergen.framepair import FramePairBatch

    meter = Meter(device, sizes.steps)
    pair = scene(sizes)
    rows = []
    for name in ("snow", "rain", "sparks", "fog"):
        count = sizes.fog_count if name == "fog" else sizes.count
        preset = load_preset(name, {"count": count} if count else None)
        parts = sample_particles(pair, preset, seed=0)
        forward, forward_backward = bench_common.render_calls(pair, parts, device)
        for label, fn in (("forward", forward), ("forward + backward", forward_backward)):
            seconds, memory = meter(fn)
            rows.append(Row("render", f"{name} ({parts.count}), {label}", seconds, memory))
    batch = 8
    preset = load_preset("snow", {"count": sizes.count} if sizes.count else None)
    records = [sample_particles(pair, preset, seed=i) for i in range(batch)]
    stacked = FramePairBatch.stack([pair] * batch)

    def batched():
        with torch.no_grad():
            render_pair(stacked, records, device=device)

    seconds, memory = meter(batched)
    rows.append(Row("render", f"snow, batch of {batch} pairs, forward", seconds, memory,
                    f"{batch / seconds:.1f} pairs/s"))
    return rows


def field_rows(device: str, sizes: Sizes) -> list[Row]:
    import bench_field
    from weathergen.engine import load_preset
    from weathergen.engine.sampling.field import make_field, field_pair_particles
    from weathergen.engine import View
    from weathergen.engine.rendering.renderer import render_first_frame

    preset = load_preset("snow-heavy")
    start = time.perf_counter()
    field = make_field(preset, 0, down=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                       frame_rate=24.0, frame="world")
    build = time.perf_counter() - start
    meter = Meter(device, 1)
    gen = torch.Generator().manual_seed(0)
    samples, renders, counts, memory = [], [], [], None
    for n in range(sizes.frames):
        pair = bench_field.frame_pair(n, gen)
        if (sizes.height, sizes.width) != (bench_field.HEIGHT, bench_field.WIDTH):
            pair = _shrunk(pair, sizes)
        views = (View(pair.intrinsics, pair.cam1_from_world, pair.depth1),
                 View(pair.intrinsics, pair.cam2_from_world, pair.depth2))
        start = time.perf_counter()
        record = field_pair_particles(field, views, (n, n + 1))
        samples.append(time.perf_counter() - start)
        counts.append(record.count)

        def render():
            with torch.no_grad():
                render_first_frame(pair, record, device=device)

        seconds, memory = meter(render)
        renders.append(seconds)
    particles = int(statistics.median(counts))
    return [Row("field", "snow-heavy: build the field", build),
            Row("field", f"snow-heavy: draw a pair's particles (~{particles})",
                statistics.median(samples), None, f"{sizes.frames} frames"),
            Row("field", "snow-heavy: render a frame", statistics.median(renders), memory,
                f"{sizes.frames} frames")]


def _shrunk(pair, sizes: Sizes):
    """``pair`` cut to the dry run's size (top-left corner; the intrinsics keep the centre)."""
    h, w = sizes.height, sizes.width
    cut = {k: getattr(pair, k)[..., :h, :w].contiguous()
           for k in ("image1", "image2", "depth1", "depth2")}
    k = pair.intrinsics.clone()
    k[0, 2], k[1, 2] = (w - 1) / 2, (h - 1) / 2
    return dataclasses.replace(pair, intrinsics=k, **cut)


def training_rows(device: str, sizes: Sizes) -> list[Row]:
    from weathergen.training import RandomCrop, WeatherAugment, collate_pairs

    samples = bench_common.training_samples(sizes.height, sizes.width, sizes.batch)
    batch = collate_pairs(samples).to(device)
    meter = Meter(device, sizes.steps)
    rows = []
    overrides = {"count": sizes.count} if sizes.count else None
    for preset in ("snow", "rain", "snow-light"):
        aug = WeatherAugment(preset, p=1.0, seed=0,
                             overrides=overrides if preset != "snow-light" else None)
        seconds, memory = meter(lambda: aug.apply_batch(batch))
        rows.append(Row("training", f"weather of a batch of {sizes.batch}: {preset}", seconds,
                        memory))
    cropped = RandomCrop(sizes.crop, seed=0).apply_batch(collate_pairs(samples)).to(device).pairs
    for name in sizes.train_models:
        seconds, memory = meter(_training_step(name, sizes, device, cropped))
        rows.append(Row("training", f"{name} training step, batch of {sizes.batch} "
                                    f"{sizes.crop[0]}x{sizes.crop[1]}", seconds, memory))
    return rows


def _training_step(name: str, sizes: Sizes, device: str, batch) -> Callable[[], object]:
    """One RAFT training step of network ``name`` on ``batch`` (a FramePairBatch), as a call."""
    from weathergen.models import build_model
    from weathergen.training import raft_optimizer, train_step

    model = build_model(name, iters=sizes.iters or 12).to(device)
    model.requires_grad_(True).train()
    optimizer, scheduler = raft_optimizer(model, steps=1000)
    return lambda: train_step(model, optimizer, scheduler, batch.image1, batch.image2, batch.flow,
                              batch.flow_valid)


def attack_rows(device: str, sizes: Sizes) -> list[Row]:
    import bench_batch

    rows = []
    for batch in sizes.attack_batches:
        r = bench_batch.measure(sizes.attack_model, "snow", sizes.width, sizes.height,
                                sizes.iters or 12, sizes.steps, batch, device, count=sizes.count)
        rows.append(Row("attack batch", f"{sizes.attack_model}, batch of {batch}: a step",
                        r["step_seconds"], r["memory_gib"] if device.startswith("cuda") else None,
                        f"{r['pair_steps_per_second']:.2f} pair-steps/s"))
        if device.startswith("cuda"):
            torch.cuda.empty_cache()
    return rows


def table_rows(device: str, sizes: Sizes) -> list[Row]:
    """The paper's networks' attack at their best batch size in the paper's precision
    (:mod:`bench_tables`), and the GPU-hours of the paper's Tables 2-5 that follow."""
    import bench_tables as bt

    quick = sizes.width < 1024
    tsizes = bt.Sizes(width=sizes.width, height=sizes.height, iters=sizes.iters, count=sizes.count,
                      batch_sizes=(1, 2) if quick else (1, 2, 4, 8, 16), steps=sizes.steps)
    networks = [sizes.attack_model] if quick else list(bt.PAPER_NETWORKS)
    results = bt.run_measurements(device, tsizes, networks, ["paper"], bt.Options(),
                                  budget_s=30.0 if not quick else math.inf, log=lambda s: None)
    rows = []
    for r in results:
        if r.attack is None:
            rows.append(Row("tables", f"{r.network}: attack", note=r.stop, failed=True))
            continue
        best = r.batches[r.best_batch]
        rows.append(Row("tables", f"{r.network}: attack step at batch {r.best_batch} (paper "
                                  f"precision)", best["step_seconds"], best["memory_gib"],
                        f"{r.attack:.2f} pair-steps/s; network alone {r.network_share:.0%} of "
                        f"a step; {r.stop}"))
    tps = bt.best_throughputs(results, "paper")
    if tps:
        hours = bt.all_hours(bt.paper_runs(), tps)["all"]
        rows.append(Row("tables", f"Tables 2-5 on Sintel, {len(tps)} network(s): "
                                  f"{hours['total']:.1f} GPU-hours",
                        note=f"Table 4: {hours['4']:.1f} h, Table 3: {hours['3']:.1f} h, "
                             f"Table 5: {hours['5']:.1f} h, Table 2: {hours['2']:.1f} h"))
    return rows


def every_network() -> list[str]:
    """Every registered network, in the tables' order (:func:`bench_models.every_network`)."""
    import bench_models

    return bench_models.every_network()


def network_rows(device: str, sizes: Sizes, models) -> list[Row]:
    import bench_models

    rows = []
    for name in models:
        for backward in (False, True):
            r = bench_models.measure(name, sizes.width, sizes.height, sizes.iters, backward, False,
                                     0, device, sizes.steps)
            label = "forward + backward" if backward else "forward"
            rows.append(Row("networks", f"{name}, {label}", r["seconds"],
                            r["peak_gib"] if device.startswith("cuda") else None,
                            "" if r["finite"] else "NOT finite", failed=not r["finite"]))
            if device.startswith("cuda"):
                torch.cuda.empty_cache()
    return rows


_SUMMARY = re.compile(r"(\d+) (passed|failed|skipped|errors?|deselected|xfailed|xpassed)")


def pytest_counts(output: str) -> dict[str, int]:
    """The counts of pytest's last summary line (``{"passed": 5, "skipped": 1}``)."""
    lines = [line for line in output.strip().splitlines() if _SUMMARY.search(line)]
    if not lines:
        return {}
    return {kind.rstrip("s") if kind.startswith("error") else kind: int(n)
            for n, kind in _SUMMARY.findall(lines[-1])}


def test_rows(device: str) -> list[Row]:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-m", "cuda", "-p",
                           "no:cacheprovider", str(ROOT / "tests")], cwd=ROOT,
                          capture_output=True, text=True)
    seconds = time.perf_counter() - start
    counts = pytest_counts(done.stdout)
    bad = counts.get("failed", 0) + counts.get("error", 0)
    note = ", ".join(f"{n} {kind}" for kind, n in counts.items()) or "no summary line"
    rows = [Row("tests", "pytest -m cuda", seconds, None, note,
                failed=done.returncode != 0 or not counts.get("passed") or bool(bad))]
    for line in done.stdout.splitlines():
        if line.startswith(("FAILED ", "ERROR ")):
            rows.append(Row("tests", line.split(" ", 1)[1][:110], note="failed", failed=True))
    return rows


# -- the table ------------------------------------------------------------------------------------

def table(rows: list[Row], title: str) -> str:
    """The Markdown table of ``rows`` under ``title``."""
    out = [title, "", "| area | what | seconds | GPU memory (GiB) | note |", "|---|---|---:|---:|---|"]
    for r in rows:
        seconds = "–" if r.seconds is None else f"{r.seconds:.3f}"
        memory = "–" if r.memory_gib is None else f"{r.memory_gib:.2f}"
        note = ("FAILED: " if r.failed else "") + r.note
        out.append(f"| {r.area} | {r.what} | {seconds} | {memory} | {note} |")
    return "\n".join(out)


AREAS = {"render": render_rows, "field": field_rows, "training": training_rows,
         "attack batch": attack_rows, "tables": table_rows}


def run(device: str, sizes: Sizes, models, tests: bool,
        progress: Optional[Callable[[str, list], None]] = None) -> list[Row]:
    """Every area's rows; an area that raises becomes one failed row naming the error.

    ``progress(area, rows_so_far)`` is called after each area (the CLI prints the area's rows and
    rewrites the JSON file, so a run cut short still leaves the areas it finished)."""
    rows = test_rows(device) if tests else []
    if progress and tests:
        progress("tests", rows)
    areas = dict(AREAS, networks=lambda d, s: network_rows(d, s, models))
    for area, measure in areas.items():
        try:
            rows += measure(device, sizes)
        except Exception as exc:              # one area's failure must not hide the others
            rows.append(Row(area, "(the area stopped)", note=f"{type(exc).__name__}: {exc}"[:200],
                            failed=True))
        if device.startswith("cuda"):
            torch.cuda.empty_cache()
        if progress:
            progress(area, rows)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="cuda or cuda:N (cpu: the dry run)")
    parser.add_argument("--quick", action="store_true",
                        help="tiny inputs, no tests: a dry run of the table (with --device cpu)")
    parser.add_argument("--models", nargs="+", default=None,
                        help="networks to measure (default: every registered one)")
    parser.add_argument("--no-tests", action="store_true", help="skip the CUDA tests")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    parser.add_argument("--probe", action="store_true",
                        help="only say whether CUDA is there (exit 2 and one line if not)")
    args = parser.parse_args(argv)
    problem = cuda_problem(args.device)
    if problem:
        print(problem, file=sys.stderr)
        return 2
    if args.probe:
        return 0
    if args.device == "cpu" and not args.quick:
        print("gpu-check: --device cpu is the dry run and needs --quick", file=sys.stderr)
        return 2
    sizes = QUICK if args.quick else Sizes()
    torch.manual_seed(0)
    models = args.models or every_network()
    title = (f"gpu-check on {device_name(args.device)}, torch {torch.__version__}, "
             f"{sizes.width}x{sizes.height}" + (" (dry run: tiny inputs)" if args.quick else ""))

    machine, measured_on = bench_common.gpu_machine(args.device), tree()

    def write_json(rows: list[Row]) -> None:
        if args.json:
            bench_common.write_atomic(args.json, json.dumps(
                {"title": title, "machine": machine, "tree": measured_on,
                 "rows": [dataclasses.asdict(r) for r in rows]}, indent=1))
            gpu_figures.write_page(args.json.with_name(gpu_figures.PAGE), args.json,
                                   args.json.with_name(gpu_figures.SESSION))

    def progress(area: str, rows: list[Row]) -> None:
        print(f"gpu-check: {area} done", file=sys.stderr, flush=True)
        write_json(rows)

    rows = run(args.device, sizes, models, tests=not (args.quick or args.no_tests), progress=progress)
    print(table(rows, title))
    write_json(rows)
    failed = [r for r in rows if r.failed]
    if failed:
        print(f"\n{len(failed)} row(s) failed.", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
