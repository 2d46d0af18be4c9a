"""What weather augmentation costs in training, against a RAFT training step on the same batch.

A batch of 6 Sintel-size pairs (1024 x 436, a textured scene with a near block, moving cameras) as
RAFT's Sintel stage uses it: the weather is rendered into the full frames, then every pair is
cropped to 368 x 768. Prints, per preset and with every pair getting weather (``p = 1``; at the
paper's ``p = 0.5`` the cost halves):

- *per sample*: :class:`WeatherAugment` applied to the 6 pairs one by one on the CPU, the time the
  DataLoader's workers spend on a batch (hidden behind the step when there are enough workers);
- *per batch*: :meth:`WeatherAugment.apply_batch` on the device, particle sampling included (on
  the CPU) and, with the particles prepared in the workers, the batched render alone (the
  engine's one render core, ragged: both paths give the same frames);
- for every render of a prepared batch, the number of tensor operations it dispatches (about one
  kernel launch each on a GPU, where their count rather than their arithmetic sets the time) and
  of host synchronisations among them (``nonzero``, ``unique``, ``.item()``, ``.tolist()``), set
  against the same counts for the training step (counted on a small crop: a step's operations do
  not depend on the image size): without a GPU, the share of launches is the estimate of the
  weather's share of a GPU step (on the CPU also with the larger chunks a GPU uses, and
  counting the host-side bookkeeping a GPU count leaves out);

and the time of one training step (forward with every iteration, sequence loss, backward, AdamW)
of RAFT-small and, with ``--model raft`` or on a GPU, full RAFT, on the cropped batch. Target:
the weather under 10 % of the step. A benchmark, not a test: nothing here fails on slow machines.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import bench_common  # noqa: E402  (the training batch)
import bench_core  # noqa: E402  (the GPU's chunking, as its operation counts use it)

from weathergen.engine import render  # noqa: E402
from weathergen.models import build_model  # noqa: E402
from weathergen.training import (RandomCrop, WeatherAugment,  # noqa: E402
                                 collate_pairs, raft_optimizer, train_step)

HEIGHT, WIDTH, BATCH, CROP = 436, 1024, 6, (368, 768)


#: Operators that wait for the device (their result's size or value goes to the host).
SYNC_OPS = ("nonzero", "unique", "_unique", "_unique2", "unique_dim", "unique_consecutive",
            "_local_scalar_dense", "masked_select", "equal", "is_nonzero", "repeat_interleave")


class OpCounter(TorchDispatchMode):
    """Counts the tensor operations dispatched while active that touch a tensor on ``device``
    (on a GPU: about one kernel launch each; the CPU-side bookkeeping is left out), and the host
    synchronisations among them. On the CPU every operation counts."""

    def __init__(self, device: torch.device):
        super().__init__()
        self.device_type = torch.device(device).type
        self.ops = 0
        self.syncs = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        tensors = [a for a in torch.utils._pytree.tree_leaves((args, kwargs))
                   if isinstance(a, torch.Tensor)]
        if self.device_type == "cpu" or any(t.device.type == self.device_type for t in tensors):
            self.ops += 1
            if func.__name__.split(".")[0] in SYNC_OPS:
                self.syncs += 1
        return func(*args, **(kwargs or {}))


def count_ops(fn, device) -> tuple[int, int]:
    """(tensor operations, host synchronisations) on ``device`` of one call of ``fn``."""
    counter = OpCounter(device)
    with counter:
        fn()
    return counter.ops, counter.syncs


def flat_arguments(batch) -> tuple:
    """The arguments of :func:`~weathergen.engine.render` for a batch with prepared particles."""
    p = batch.pairs
    return (p.image1, p.image2, p.depth1, p.depth2, p.intrinsics, p.cam1_from_world,
            p.cam2_from_world, list(batch.particles))


def timed(fn, repeats: int, sync, warm_up: bool = True) -> float:
    """Median seconds of ``repeats`` calls, after one warm-up call if asked."""
    if warm_up:
        fn()
        sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--presets", default="snow,rain,snow-light",
                        help="comma-separated presets (of either model)")
    parser.add_argument("--model", action="append", default=None,
                        help="raft-small and/or raft (default: raft-small on the CPU, both on a GPU)")
    parser.add_argument("--repeats", type=int, default=None,
                        help="timed repeats (default 1 on the CPU, 5 on a GPU)")
    parser.add_argument("--iters", type=int, default=12, help="RAFT iterations in the step")
    parser.add_argument("--threads", type=int, default=min(2, os.cpu_count() or 1),
                        help="CPU threads")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    gpu = device.type == "cuda"
    torch.set_num_threads(args.threads)
    repeats = args.repeats or (5 if gpu else 1)
    models = args.model or (["raft-small", "raft"] if gpu else ["raft-small"])
    sync = torch.cuda.synchronize if gpu else (lambda: None)
    name = torch.cuda.get_device_name(device) if gpu else f"CPU, {torch.get_num_threads()} thread(s)"
    print(f"training cost: batch of {BATCH} pairs {WIDTH}x{HEIGHT}, cropped to "
          f"{CROP[0]}x{CROP[1]} after the weather; {name}; median of {repeats}")

    samples = bench_common.training_samples(HEIGHT, WIDTH, BATCH, wall=True)
    crop = RandomCrop(CROP, seed=0)
    batch_cpu = collate_pairs(samples)
    batch_dev = batch_cpu.to(device)

    weather_times, op_counts = {}, {}
    for preset in args.presets.split(","):
        aug = WeatherAugment(preset, p=1.0, seed=0)
        per_sample = timed(lambda: [aug(s) for s in samples], repeats, lambda: None)
        prepared = collate_pairs([aug.prepare(s) for s in samples]).to(device)
        batched = timed(lambda: aug.apply_batch(batch_dev), repeats, sync)
        render_only = timed(lambda: aug.apply_batch(prepared), repeats, sync)
        weather_times[preset] = {
            "per sample (CPU)": per_sample,
            f"per batch ({device.type})": batched,
            f"prepared, render only ({device.type})": render_only}
        op_counts[preset] = {"default chunks": count_ops(lambda: aug.apply_batch(prepared),
                                                         device)}
        if device.type == "cpu":    # the chunks a GPU with free memory would use, views not cut
            with bench_core._gpu_split():
                op_counts[preset]["GPU-size chunks"] = count_ops(
                    lambda: render(*flat_arguments(prepared), chunk_elements=1 << 25), device)

    cropped = crop.apply_batch(batch_cpu).to(device)
    p = cropped.pairs
    small = RandomCrop((64, 128), seed=0).apply_batch(batch_cpu).to(device).pairs
    step_times, step_ops = {}, {}
    for model_name in models:
        model = build_model(model_name, iters=args.iters).to(device)
        model.requires_grad_(True).train()
        optimizer, scheduler = raft_optimizer(model, steps=1000)
        step = functools.partial(train_step, model, optimizer, scheduler)
        step_times[model_name] = timed(
            functools.partial(step, p.image1, p.image2, p.flow, p.flow_valid), repeats, sync,
            warm_up=gpu)  # CPU: keep it short
        step_ops[model_name] = count_ops(
            functools.partial(step, small.image1, small.image2, small.flow, small.flow_valid), device)
        del model, optimizer, scheduler, step
        if gpu:
            torch.cuda.empty_cache()

    print(f"{'RAFT training step':<30}" + "".join(f"{m:>16}" for m in step_times))
    print(f"{'':<30}" + "".join(f"{t:>15.2f}s" for t in step_times.values()))
    width = 44
    print(f"{'weather, p = 1':<{width}}{'seconds':>10}" + "".join(f"{'% of ' + m:>16}"
                                                                 for m in step_times))
    for preset, rows in weather_times.items():
        for label, t in rows.items():
            print(f"{preset + ': ' + label:<{width}}{t:>9.3f}s"
                  + "".join(f"{100 * t / s:>15.1f}%" for s in step_times.values()))
    where = "every op" if device.type == "cpu" else f"ops on {device.type}"
    print(f"{'tensor operations (' + where + ')':<{width}}{'ops':>10}{'syncs':>8}"
          + "".join(f"{'% of ' + m + ' ops':>20}" for m in step_ops))
    for model_name, (ops, syncs) in step_ops.items():
        print(f"{model_name + ' training step':<{width}}{ops:>10}{syncs:>8}")
    for preset, counts in op_counts.items():
        for mode, (ops, syncs) in counts.items():
            print(f"{preset + ': render, ' + mode:<{width}}{ops:>10}{syncs:>8}"
                  + "".join(f"{100 * ops / s:>19.1f}%" for s, _ in step_ops.values()))


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
