"""A weather field over a long sequence: time per frame, peak memory, field sampling time.

Renders a synthetic 1024 x 436 sequence (a camera moving forward 0.1 m a frame past two depth
planes, Sintel-like focal length) with one field, the way ``weathergen render --sequence`` does:
each pair's particle record is drawn from the scene's field (both views culled) and its first
frame rendered alone. Prints the field's construction time, then per block of frames the median
sampling and rendering times and the process's peak resident memory, which must stay flat as
the sequence grows (frames stream; the field is never re-sampled). Nothing is written to disk.

    python speed/bench_field.py [--frames 200] [--preset snow-heavy] [--device cpu|cuda]

A benchmark, not a test: nothing here fails on slow machines.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from engine_scenes import pose, rotation  # noqa: E402

from weathergen.engine import load_preset  # noqa: E402
from weathergen.engine.sampling.field import make_field, field_pair_particles  # noqa: E402
from weathergen.engine import View  # noqa: E402
from weathergen.engine.rendering.renderer import render_first_frame  # noqa: E402
from weathergen.framepair import FramePair, PairId  # noqa: E402

HEIGHT, WIDTH, FOCAL = 436, 1024, 1120.0


def peak_rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def camera(n: int) -> torch.Tensor:
    """Forward 0.1 m a frame, swaying gently."""
    return pose(rotation(yaw_deg=3 * torch.sin(torch.tensor(n / 30.0)).item()),
                centre=(0.2 * torch.sin(torch.tensor(n / 50.0)).item(), 0.0, 0.1 * n))


def frame_pair(n: int, gen: torch.Generator) -> FramePair:
    k = torch.tensor([[FOCAL, 0, (WIDTH - 1) / 2], [0, FOCAL, (HEIGHT - 1) / 2], [0, 0, 1]],
                     dtype=torch.float64)
    depth = torch.full((1, HEIGHT, WIDTH), 8.0)
    depth[..., :, 700:] = 2.5
    images = [(0.2 + 0.5 * torch.rand(3, HEIGHT, WIDTH, generator=gen)) for _ in range(2)]
    c1, c2 = camera(n), camera(n + 1)
    return FramePair(id=PairId("sintel", "training", "bench", n), image1=images[0],
                     image2=images[1], depth1=depth, depth2=depth.clone(), intrinsics=k,
                     cam2_from_cam1=c2 @ torch.linalg.inv(c1), cam1_from_world=c1,
                     cam2_from_world=c2)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--preset", default="snow-heavy")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    preset = load_preset(args.preset)
    start = time.perf_counter()
    fld = make_field(preset, 0, down=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                     frame_rate=24.0, frame="world")
    build = time.perf_counter() - start
    print(f"{args.preset}: density {preset.density:g}/m3, far {preset.far:g} m, "
          f"{fld.count} particles per tile of {fld.tile:g} m; field built in {build * 1e3:.1f} ms; "
          f"{WIDTH}x{HEIGHT}, {args.frames} frames, device {args.device}, "
          f"{torch.get_num_threads()} thread(s), torch {torch.__version__}")
    print(f"{'frames':>10} {'particles':>10} {'sample s':>9} {'render s':>9} {'frame s':>8} "
          f"{'peak MiB':>9}")
    gen = torch.Generator().manual_seed(0)
    block = max(1, args.frames // 8)
    rows, samples, renders, counts = [], [], [], []
    for n in range(args.frames):
        pair = frame_pair(n, gen)
        views = (View(pair.intrinsics, pair.cam1_from_world, pair.depth1),
                 View(pair.intrinsics, pair.cam2_from_world, pair.depth2))
        t0 = time.perf_counter()
        record = field_pair_particles(fld, views, (n, n + 1))
        t1 = time.perf_counter()
        with torch.no_grad():
            image, _ = render_first_frame(pair, record, device=args.device)
        if image.is_cuda:
            torch.cuda.synchronize()
        t2 = time.perf_counter()
        samples.append(t1 - t0)
        renders.append(t2 - t1)
        counts.append(record.count)
        del image, record, pair
        if (n + 1) % block == 0 or n + 1 == args.frames:
            s, r = statistics.median(samples), statistics.median(renders)
            print(f"{n + 1 - len(samples) + 1:>4}-{n + 1:<5} {int(statistics.median(counts)):>10} "
                  f"{s:>9.3f} {r:>9.3f} {s + r:>8.3f} {peak_rss_mib():>9.0f}", flush=True)
            rows.append((s, r, peak_rss_mib()))
            samples, renders, counts = [], [], []
    if len(rows) >= 2:
        growth = rows[-1][2] - rows[0][2]
        print(f"peak memory grew by {growth:.0f} MiB from the first block to the last "
              f"({'flat' if growth < 50 else 'NOT flat'})")
    if torch.cuda.is_available() and args.device == "cpu":
        print("(CUDA is available: rerun with --device cuda for GPU figures)")


if __name__ == "__main__":
    from figures import record   # the figures file (docs/figures/bench.md)

    sys.exit(record(main))
