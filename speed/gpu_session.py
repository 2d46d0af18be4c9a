"""One short GPU session of speed measurements: the attack tables, the options that may shrink
them, and the weather of a training batch against a RAFT training step.

Run from the repository root on a machine with a CUDA GPU (the package from its source checkout)::

    bash speed/gpu_session.sh                 # figures in $OUT (or docs/figures)
    PYTHONPATH=$PWD python3 speed/gpu_session.py --out DIR [--deadline-s 330]
    python speed/gpu_session.py --device cpu --quick --out /tmp/s   # the CPU smoke test

Sections, in order, each writing ``DIR/gpu-session.json`` when it ends (a run cut short keeps
what it measured), with the machine and the tree (git commit) it ran on, and rewriting the page
``DIR/gpu.md`` from it (and from ``DIR/gpu-check.json`` where there is one:
:mod:`gpu_figures`), and printing its rows as it goes. ``DIR`` is ``--out``, else ``$OUT``, else
docs/figures (with ``--quick``: out/gpu-session, so that a smoke test leaves the figures alone):

1. ``tests``: the CUDA tests of device-side sampling (``pytest -m cuda -k "sampling_on or
   fields_views"``);
2. ``tables``: :mod:`bench_tables` for the paper's six networks in the paper's precision and in
   float32, batch sizes up to 16 within 78 GiB (an 80 GB H100's memory), and the GPU-hours of
   the paper's Tables 2-5 that follow;
3. ``sampler``: particles of paper presets and of a weather field sampled on the CPU and on the
   GPU (time per pair, the share of identical particles);
4. ``training``: the weather of a batch of 6 Sintel-size pairs (``WeatherAugment.apply_batch``)
   sampled on the CPU (today), on the device, and prepared in loader workers (render only; the
   worker's sampling time per sample beside it), against a RAFT training step on the 368x768
   crops of the batch;
5. ``options``: TF32 matrix products, RAFT's mixed precision, gradient checkpointing at larger
   batches, ``torch.compile`` of the iteration steps (last: compiling takes tens of seconds),
   each with its throughput and its flow's difference from float32 (same random weights, same
   frames).

Every section stops early when the session's deadline (``--deadline-s``, counted from the start)
comes near, saying so in its rows.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "speed"))
sys.path.insert(1, str(ROOT))
sys.path.insert(2, str(ROOT / "tests"))

import torch  # noqa: E402

import bench_common  # noqa: E402  (the clock, the machine, the training batch)
import bench_tables as bt  # noqa: E402
import gpu_figures  # noqa: E402  (the page docs/figures/gpu.md)
from figures import tree  # noqa: E402


class Session:
    """The clock, the log and the figures file of one run."""

    def __init__(self, out: Path, deadline_s: float, device: str, quick: bool):
        self.out, self.deadline_s, self.device, self.quick = out, deadline_s, device, quick
        self.start = time.perf_counter()
        self.figures: dict = {"machine": bench_common.gpu_machine(device), "tree": tree(),
                              "quick": quick, "sections": {}}
        out.mkdir(parents=True, exist_ok=True)

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def left(self) -> float:
        return self.deadline_s - self.elapsed()

    def log(self, text: str) -> None:
        print(f"[{self.elapsed():6.1f} s] {text}", flush=True)

    def save(self, section: str, figures) -> None:
        self.figures["sections"][section] = figures
        self.figures["elapsed_s"] = self.elapsed()
        path = self.out / gpu_figures.SESSION
        bench_common.write_atomic(path, json.dumps(self.figures, indent=1, default=str))
        gpu_figures.write_page(self.out / gpu_figures.PAGE, self.out / gpu_figures.CHECK, path)


# -- 1. tests ---------------------------------------------------------------------------------------

def section_tests(s: Session) -> dict:
    if not s.device.startswith("cuda"):
        return {"skipped": "no CUDA device"}
    cmd = [sys.executable, "-m", "pytest", "-q", "-m", "cuda", "-k",
           "sampling_on or fields_views", "-p", "no:cacheprovider",
           "tests/engine/test_engine_sampling.py", "tests/engine/test_engine_field.py",
           "tests/training/test_training_augment.py"]
    try:
        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                              timeout=max(30.0, min(120.0, s.left() - 240)))
    except subprocess.TimeoutExpired:
        return {"failed": "timed out"}
    tail = done.stdout.strip().splitlines()[-15:]
    for line in tail:
        s.log("  " + line)
    return {"returncode": done.returncode, "tail": tail}


# -- 2. tables --------------------------------------------------------------------------------------

def section_tables(s: Session, sizes: bt.Sizes, networks, budget_s: float) -> dict:
    results = bt.run_measurements(s.device, sizes, networks, ["paper", "float32"], bt.Options(),
                                  budget_s, log=s.log)
    print("\n" + bt.measured_table(results) + "\n", flush=True)
    runs = bt.paper_runs()
    return {"measured": [dataclasses.asdict(r) for r in results],
            "hours": bt.report_hours(runs, results, ("paper", "float32"), "GPU-hours"),
            "counts": bt.table_counts(runs)}


# -- 3. options -------------------------------------------------------------------------------------

#: (network, precision, options, batch sizes): each measured against its float32 throughput.
def option_plan(quick: bool) -> list[tuple[str, str, bt.Options, tuple]]:
    if quick:
        return [("raft-small", "tf32", bt.Options(), (1,)),
                ("raft-small", "amp", bt.Options(), (1,)),
                ("raft-small", "float32", bt.Options(checkpointing=True), (2,)),
                ("raft-small", "float32", bt.Options(compile="default", backend="aot_eager"),
                 (1,))]
    return [("flowformer", "tf32", bt.Options(), (1, 2, 4)),
            ("raft", "amp", bt.Options(), (8, 16)),
            ("raft", "float32", bt.Options(compile="default"), (8,)),
            ("flowformer", "float32", bt.Options(checkpointing=True), (4, 8, 16)),
            ("gma", "tf32", bt.Options(), (8, 16)),
            ("raft", "tf32", bt.Options(), (8, 16)),
            ("spynet", "tf32", bt.Options(), (16, 32)),
            ("raft", "float32", bt.Options(checkpointing=True), (16, 32)),
            ("gma", "paper", bt.Options(compile="default"), (8,)),
            ("flowformer", "tf32", bt.Options(compile="default"), (2,))]


def flow_difference(bench: bt.Bench, name: str, precision: str, options: bt.Options,
                    anywhere: bool) -> dict:
    """The flow of one pair with ``options`` in ``precision`` against float32 without options:
    the same random weights (seed 0), the same frames. Max and RMS difference in pixels, and the
    RMS of the float32 flow for scale."""
    flows = []
    for prec, opts in (("float32", bt.Options()), (precision, options)):
        torch.manual_seed(0)
        model = bench.model(name, bt.precision_settings(name, prec, bench.device, anywhere), opts)
        a = bench.pair.image1[None].to(bench.device)
        b = bench.pair.image2[None].to(bench.device)
        with torch.no_grad():
            flows.append(model(a, b).float().cpu())
        del model
    ref, got = flows
    diff = got - ref
    return {"max_px": float(diff.abs().max()), "rms_px": float(diff.square().mean().sqrt()),
            "flow_rms_px": float(ref.square().mean().sqrt())}


def section_options(s: Session, sizes: bt.Sizes, budget_s: float) -> dict:
    bench = bt.Bench(s.device, sizes)
    rows = []
    for name, precision, options, batches in option_plan(s.quick):
        label = f"{name} [{precision}; {options.label()}]"
        if s.left() < (100 if options.compile and not s.quick else 50):
            s.log(f"  {label}: skipped (session deadline near)")
            rows.append({"network": name, "precision": precision, "options": options.label(),
                         "skipped": "deadline"})
            continue
        try:
            r = bt.measure(bench, name, precision, options, min(budget_s, s.left() - 40), s.log,
                           anywhere=s.quick, batch_sizes=batches)
            row = dataclasses.asdict(r)
            if s.left() > (120 if options.compile and not s.quick else 40):
                row["flow_difference"] = flow_difference(bench, name, precision, options,
                                                         s.quick)
                s.log(f"  {label}: flow vs float32 {row['flow_difference']}")
        except Exception as exc:          # noqa: BLE001 - one option's failure hides no other
            row = {"network": name, "precision": precision, "options": options.label(),
                   "failed": f"{type(exc).__name__}: {exc}"[:300]}
            s.log(f"  {label}: FAILED {row['failed']}")
        rows.append(row)
        if s.device.startswith("cuda"):
            torch.cuda.empty_cache()
    return {"rows": rows}


# -- 4. sampler ------------------------------------------------------------------------------------

def section_sampler(s: Session, sizes: bt.Sizes) -> dict:
    from bench_attack import synthetic_pair
    from weathergen.engine import load_preset, sample_weather

    pair = synthetic_pair(sizes.width, sizes.height)
    on_device = pair.to(s.device)
    overrides = {"count": sizes.count} if sizes.count else None
    rows = []
    for name in ("snow", "rain", "sparks", "snow-light"):
        preset = load_preset(name, overrides if name != "snow-light" else None)

        def sample(p, on=None):
            return sample_weather(p, preset, 1, sample_on=on, device=on, frame_rate=24.0)

        try:
            cpu_s = bench_common.timed(lambda: sample(pair), "cpu", 3)
            dev_s = bench_common.timed(lambda: sample(on_device, s.device), s.device, 3)
            a, b = sample(pair), sample(on_device, s.device)
        except Exception as exc:          # noqa: BLE001 - one row's failure hides no other
            rows.append({"preset": name, "failed": f"{type(exc).__name__}: {exc}"[:300]})
            s.log(f"  sample {name}: FAILED {rows[-1]['failed']}")
            continue
        same = float((a.position == b.position.cpu()).all(1).float().mean()) \
            if a.count == b.count and a.count else float(a.count == b.count)
        row = {"preset": name, "count": a.count, "cpu_s": cpu_s, "device_s": dev_s,
               "same_count": a.count == b.count, "identical_particles": same}
        s.log(f"  sample {name}: CPU {cpu_s * 1000:.1f} ms, {s.device} {dev_s * 1000:.1f} ms per "
              f"pair, {same:.2%} of the particles identical")
        rows.append(row)
    return {"rows": rows}


# -- 5. training -----------------------------------------------------------------------------------

def section_training(s: Session, sizes: bt.Sizes, batch: int, crop: tuple, repeats: int) -> dict:
    import gpu_check
    from weathergen.training import RandomCrop, WeatherAugment, collate_pairs

    samples = bench_common.training_samples(sizes.height, sizes.width, batch)
    on_device = collate_pairs(samples).to(s.device)
    cropped = RandomCrop(crop, seed=0).apply_batch(collate_pairs(samples)).to(s.device).pairs
    step_sizes = gpu_check.Sizes(iters=sizes.iters)
    step = gpu_check._training_step("raft" if not s.quick else "raft-small", step_sizes, s.device,
                                    cropped)
    step_s = bench_common.timed(step, s.device, repeats)
    s.log(f"  RAFT training step, batch {batch} {crop[0]}x{crop[1]}: {step_s:.3f} s")
    rows = [{"what": "raft training step", "seconds": step_s}]
    overrides = {"count": sizes.count} if sizes.count else None
    for preset in ("snow", "rain", "snow-light"):
        kw = dict(p=1.0, seed=0, overrides=overrides if preset != "snow-light" else None)
        cpu_aug = WeatherAugment(preset, **kw)
        dev_aug = WeatherAugment(preset, sample_on="device", **kw)
        t0 = time.perf_counter()
        prepared = [cpu_aug.prepare(x) for x in samples]
        worker_s = (time.perf_counter() - t0) / len(samples)
        ready = collate_pairs(prepared).to(s.device)
        for what, fn in (("sampled on the CPU (threads)", lambda: cpu_aug.apply_batch(on_device)),
                         ("sampled on the device", lambda: dev_aug.apply_batch(on_device)),
                         ("prepared in loader workers: render only",
                          lambda: cpu_aug.apply_batch(ready))):
            label = f"weather of a batch of {batch}: {preset}, {what}"
            try:
                seconds = bench_common.timed(fn, s.device, repeats)
            except Exception as exc:      # noqa: BLE001 - one row's failure hides no other
                rows.append({"what": label, "failed": f"{type(exc).__name__}: {exc}"[:300]})
                s.log(f"  {label}: FAILED {rows[-1]['failed']}")
                continue
            rows.append({"what": label, "seconds": seconds,
                         "share_of_training_step": seconds / step_s})
            s.log(f"  {label}: {seconds:.3f} s ({seconds / step_s:.0%} of a RAFT step)")
        rows.append({"what": f"{preset}: a loader worker's prepare() per sample (CPU, 1 process)",
                     "seconds": worker_s})
        s.log(f"  {preset}: prepare() in a worker {worker_s:.3f} s per sample")
    return {"rows": rows}


# -- the run -----------------------------------------------------------------------------------------

def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--out", type=Path, default=None,
                        help="the folder of gpu-session.json and gpu.md (default: $OUT, else "
                             "docs/figures; with --quick: $OUT, else out/gpu-session)")
    parser.add_argument("--deadline-s", type=float, default=None,
                        help="seconds from the start after which sections are cut short "
                             "(default 300; with --quick 3600)")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (the CPU smoke test)")
    parser.add_argument("--sections", nargs="+",
                        default=["tests", "tables", "sampler", "training", "options"])
    args = parser.parse_args(argv)
    if args.device.startswith("cuda") and not torch.cuda.is_available():
        print("gpu_session: no CUDA device here (--device cpu --quick for the smoke test)",
              file=sys.stderr)
        return 2
    if args.out is None:
        args.out = Path(os.environ.get("OUT") or ("out/gpu-session" if args.quick
                                                  else gpu_figures.FOLDER))
    deadline = args.deadline_s if args.deadline_s is not None else (3600.0 if args.quick
                                                                     else 300.0)
    s = Session(args.out, deadline, args.device, args.quick)
    s.log(f"gpu_session on {s.figures['machine']}, out {args.out}")
    if args.quick:
        sizes = dataclasses.replace(bt.QUICK, batch_sizes=(1, 2))
        networks, budget, train = ["raft-small", "spynet"], 30.0, dict(batch=2, crop=(48, 96),
                                                                        repeats=1)
    else:
        sizes = bt.Sizes(batch_sizes=(1, 4, 8, 16), steps=2)
        networks, budget, train = list(bt.PAPER_NETWORKS), 20.0, dict(batch=6, crop=(368, 768),
                                                                       repeats=3)
        bt.cap_memory(args.device, 78.0)
    sections = {
        "tests": lambda: section_tests(s),
        "tables": lambda: section_tables(s, sizes, networks, budget),
        "options": lambda: section_options(s, sizes, budget),
        "sampler": lambda: section_sampler(s, sizes),
        "training": lambda: section_training(s, bt.Sizes(width=sizes.width, height=sizes.height,
                                                         iters=sizes.iters, count=sizes.count),
                                             **train),
    }
    failed = []
    for name in args.sections:
        if s.left() < 20:
            s.log(f"section {name}: skipped (deadline)")
            s.save(name, {"skipped": "deadline"})
            continue
        s.log(f"section {name} ...")
        try:
            figures = sections[name]()
        except Exception as exc:          # noqa: BLE001 - one section's failure hides no other
            traceback.print_exc()
            figures = {"failed": f"{type(exc).__name__}: {exc}"[:500]}
            failed.append(name)
        s.save(name, figures)
        if args.device.startswith("cuda"):
            torch.cuda.empty_cache()
        s.log(f"section {name} done")
    s.log(f"finished; figures in {args.out / gpu_figures.SESSION} and {args.out / gpu_figures.PAGE}"
          + (f"; FAILED sections: {', '.join(failed)}" if failed else ""))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
