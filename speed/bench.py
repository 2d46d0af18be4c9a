"""Speed and memory of the particle engine at Sintel resolution (1024 x 436), on the CPU.

Prints, per main preset: sampling time, render time (forward, no gradient), forward + backward
time (gradients for both offsets, colour and transparency, beta = 30), peak resident memory
during the forward + backward, and the bytes of the pair's metadata file as a render writes it
(the particle record, the pair's identity and file list); then how the render time grows
with the particle count and with the number of motion-blur samples. Times are medians of a few
runs. A benchmark, not a test: nothing here fails on slow machines.

Clock: the wall clock by default; ``BENCH_CLOCK=cpu`` times the process's CPU time.
Threads: one by default (``BENCH_THREADS=N`` to change), the setting the CLI uses for every
worker. One thread gives figures that hold on a shared, busy machine; torch's default (one
thread per core) is faster only on an idle one and can be many times slower on a loaded one.
The fog rows also time the exact path (``coarse_side=None``) beside the default coarse path
for large billboards.
"""

from __future__ import annotations

import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from engine_scenes import plane_pair, pose, rotation  # noqa: E402

from weathergen.engine import (BETA_ATTACK, load_preset, render_pair,  # noqa: E402
                               sample_particles)
from weathergen.framepair import PairId  # noqa: E402
from weathergen.outputs import PairOutput, pair_metadata, write_metadata  # noqa: E402

HEIGHT, WIDTH = 436, 1024
REPEATS = int(os.environ.get("BENCH_REPEATS", "5"))
# BENCH_CLOCK=cpu times the process's CPU time instead of the wall clock: with one thread on a
# busy shared machine it stays close to what an idle machine's wall clock would show.
CLOCK = time.process_time if os.environ.get("BENCH_CLOCK") == "cpu" else time.perf_counter
BEST: list = []  # best-of-run times, printed beside medians: shared machines are noisy


def scene():
    cam1 = pose(rotation(roll_deg=3, pitch_deg=-5))
    cam2 = pose(rotation(roll_deg=3, pitch_deg=-4, yaw_deg=1), centre=(0.05, 0.0, 0.1))
    pair = plane_pair(HEIGHT, WIDTH, depth=6.0, near_block=True, cam1_from_world=cam1,
                      cam2_from_world=cam2)
    pair.depth1[..., :, 600:] = 2.0   # a second plane so that occlusion matters
    pair.depth2[..., :, 600:] = 2.0
    return pair


def median_time(fn, repeats=REPEATS):
    fn()  # warm-up: first-call allocations and kernel selection
    times = []
    for _ in range(repeats):
        start = CLOCK()
        fn()
        times.append(CLOCK() - start)
    BEST.append(min(times))
    return statistics.median(times)


def reset_peak_rss():
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def peak_rss_mib():
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def forward(pair, parts, **kw):
    with torch.no_grad():
        return render_pair(pair, parts, **kw)


def forward_backward(pair, parts, **kw):
    leaves = {name: getattr(parts, name).clone().requires_grad_(True)
              for name in ("offset1", "offset2", "color", "transparency")}
    out = render_pair(pair, parts.replace(**leaves), beta=BETA_ATTACK, **kw)
    (out.image1.sum() + out.image2.sum()).backward()


def metadata_bytes(parts, preset, name: str) -> int:
    """Size of the metadata file a render writes for a Sintel pair with these particles."""
    pair_id = PairId("sintel", "training", "ambush_2", 1)
    with tempfile.TemporaryDirectory() as tmp:
        out = PairOutput.of(tmp, pair_id, f"{name}_clean", "png", geometry=True)
        meta = pair_metadata(parts, pair_id, 1234567890123, preset.to_dict(), name)
        meta["visible1"] = meta["visible2"] = np.array(parts.count, np.int64)
        meta["files"] = np.array(json.dumps([str(p.relative_to(tmp))
                                             for p in out.files(with_flow=True)]))
        return write_metadata(out.metadata, meta).stat().st_size


def main():
    torch.set_num_threads(int(os.environ.get("BENCH_THREADS", "1")))
    pair = scene()
    print(f"weathergen engine benchmark: {WIDTH}x{HEIGHT}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, medians of {REPEATS}, "
          f"{'CPU time' if CLOCK is time.process_time else 'wall clock'}")
    print(f"peak MiB is the process's peak resident memory during one forward + backward; "
          f"before any rendering it is {peak_rss_mib():.0f} MiB (torch itself)")
    figures = {}
    print(f"{'preset':8} {'count':>6} {'sample s':>9} {'render s':>9} {'fwd+bwd s':>10} "
          f"{'bwd/fwd':>8} {'peak MiB':>9} {'meta kB':>8}")
    for name in ("snow", "rain", "sparks", "fog"):
        preset = load_preset(name)
        sample_s = median_time(lambda: sample_particles(pair, preset, seed=0))
        parts = sample_particles(pair, preset, seed=0)
        render_s = median_time(lambda: forward(pair, parts))
        fb_s = median_time(lambda: forward_backward(pair, parts))
        reset_peak_rss()
        forward_backward(pair, parts)
        peak = peak_rss_mib()
        size = metadata_bytes(parts, preset, name)
        figures[name] = (sample_s, render_s, fb_s, size)
        print(f"{name:8} {parts.count:6d} {sample_s:9.3f} {render_s:9.3f} {fb_s:10.3f} "
              f"{fb_s / render_s:8.2f} {peak:9.0f} {size / 1000:8.1f}   "
              f"(best: {BEST[-3]:.3f} / {BEST[-2]:.3f} / {BEST[-1]:.3f})")

    print("\nfog: exact splat of every billboard pixel vs the coarse path (coarse_side=None / "
          "default):")
    parts = sample_particles(pair, load_preset("fog"), seed=0)
    exact_f = median_time(lambda: forward(pair, parts, coarse_side=None), 3)
    fast_f = median_time(lambda: forward(pair, parts), 3)
    exact_fb = median_time(lambda: forward_backward(pair, parts, coarse_side=None), 3)
    fast_fb = median_time(lambda: forward_backward(pair, parts), 3)
    print(f"  forward {exact_f:.3f} s -> {fast_f:.3f} s ({exact_f / fast_f:.0f}x); forward + "
          f"backward {exact_fb:.3f} s -> {fast_fb:.3f} s ({exact_fb / fast_fb:.0f}x)")

    print("\nrender time vs particle count (snow, forward):")
    for count in (1000, 2000, 3000, 4000, 5000):
        parts = sample_particles(pair, load_preset("snow", {"count": count}), seed=0)
        print(f"  {count:5d} particles: {median_time(lambda: forward(pair, parts)):.3f} s "
              f"(best {BEST[-1]:.3f})")

    print("\nrender time vs blur samples (rain, forward; fwd+bwd):")
    for samples in (1, 5, 10, 20, 40):
        preset = load_preset("rain", {"blur_samples": samples})
        parts = sample_particles(pair, preset, seed=0)
        fwd = median_time(lambda: forward(pair, parts))
        best = BEST[-1]
        print(f"  {samples:3d} samples: {fwd:.3f} s (best {best:.3f}); fwd+bwd "
              f"{median_time(lambda: forward_backward(pair, parts), 3):.3f} s")

    print("\nmemory bound: 5000 particles x 20 blur samples (rain, forward + backward):")
    parts = sample_particles(pair, load_preset("rain", {"count": 5000}), seed=0)
    reset_peak_rss()
    start = time.perf_counter()
    forward_backward(pair, parts)
    print(f"  {time.perf_counter() - start:.3f} s, peak resident {peak_rss_mib():.0f} MiB")

    print(f"\ntargets ({torch.get_num_threads()} thread(s), medians):")
    snow, rain = figures["snow"], figures["rain"]
    ratio = max(f[2] / f[1] for f in figures.values())
    meta = max(f[3] for f in figures.values()) / 1000
    for label, value, target, unit in (
            ("snow sample + render", snow[0] + snow[1], 1.0, "s"),
            ("rain sample + render", rain[0] + rain[1], 3.0, "s"),
            ("forward + backward / forward, worst preset", ratio, 3.0, "x"),
            ("fog forward, exact / coarse path", exact_f / fast_f, 20.0, "x"),
            ("metadata per pair, largest", meta, 60.0, "kB")):
        above = label.startswith("fog")
        verdict = "ok" if (value >= target if above else value <= target) else "MISSED"
        print(f"  {label:44} {value:8.2f} {unit:2} (target {'>=' if above else '<='} "
              f"{target:g} {unit})  {verdict}")


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
