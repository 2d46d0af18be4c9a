"""Opacity of the atmosphere by depth band, for every fog and precipitation rung (docs/engine.md,
"The atmosphere").

The scene is metric and synthetic, so that the table is reproducible without any dataset: a
KITTI-like camera (1242 x 375, f = 721 px, 1.65 m above a flat road, looking level), the road's
depth growing from 5 m at the bottom of the image to 120 m at the horizon band, a row of
building fronts at 80 m over the middle third of the columns, and the sky (the far depth readers
give it, 1000 m) above. For each preset the atmosphere alone is rendered (its particles left
out) with the pair's own ``auto`` airlight, and the mean opacity ``1 − t`` of frame 1 is printed
for the pixels whose camera depth lies in 5–10, 20–40 and 40–80 m, and for the sky, as a
Markdown table. Heterogeneous rungs are averaged over four field seeds.

    python speed/atmosphere_bands.py [--presets mist fog-light ...] [--seeds 4]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PRESETS = ("mist", "fog-light", "fog-moderate", "fog-heavy", "rain-light", "rain-moderate",
           "rain-heavy", "snow-light", "snow-moderate", "snow-heavy")
BANDS = ((5.0, 10.0), (20.0, 40.0), (40.0, 80.0))
SKY = 1000.0
HEIGHT, WIDTH, FOCAL, CAMERA_HEIGHT = 375, 1242, 721.5377, 1.65


def metric_scene():
    """The road, the fronts and the sky (see the module doc) as a two-frame pair, the camera
    moving 0.8 m forward between the frames."""
    from weathergen.framepair import FramePair, PairId

    cy = 172.85
    k = torch.tensor([[FOCAL, 0, 609.56], [0, FOCAL, cy], [0, 0, 1]], dtype=torch.float64)
    v = torch.arange(HEIGHT, dtype=torch.float64)[:, None].expand(HEIGHT, WIDTH)
    below = (v - cy).clamp(min=1e-6)
    road = (FOCAL * CAMERA_HEIGHT / below).clamp(max=120.0)
    depth = torch.where(v > cy + FOCAL * CAMERA_HEIGHT / 120.0, road, torch.full_like(v, SKY))
    cols = torch.arange(WIDTH)[None, :].expand(HEIGHT, WIDTH)
    front = (cols >= WIDTH // 3) & (cols < 2 * WIDTH // 3) & (v > cy - 60) & (depth > 80.0)
    depth = torch.where(front, torch.full_like(depth, 80.0), depth)
    g = torch.Generator().manual_seed(0)
    image = (0.25 + 0.35 * torch.rand(3, HEIGHT, WIDTH, generator=g)).float()
    image[:, depth >= SKY] = 0.85                                   # a bright, overcast sky
    cam1 = torch.eye(4, dtype=torch.float64)
    cam2 = cam1.clone()
    cam2[2, 3] = -0.8
    d = depth[None].float()
    return FramePair(id=PairId("synthetic", "metric", "road", 0), image1=image,
                     image2=image.clone(), depth1=d, depth2=d.clone(), intrinsics=k,
                     cam2_from_cam1=cam2, cam1_from_world=cam1, cam2_from_world=cam2)


def opacity(pair, name: str, seed: int) -> torch.Tensor:
    """Frame 1's opacity of the preset's atmosphere alone. Shape: (H, W)."""
    from weathergen.engine import load_preset, render_pair, sample_weather

    record = sample_weather(pair, load_preset(name), seed, frame_rate=10.0)
    empty = record.select(torch.zeros(record.count, dtype=torch.bool))
    with torch.no_grad():
        return render_pair(pair, empty).opacity1[0, 0].double()


def table(names, seeds: int) -> list[str]:
    from weathergen.engine import load_preset
    from weathergen.engine.weather.atmosphere import extinction_visibility

    pair = metric_scene()
    depth = pair.depth1[0].double()
    masks = [(depth >= lo) & (depth < hi) for lo, hi in BANDS] + [depth >= SKY]
    lines = ["| preset | visibility | " + " | ".join(f"{lo:g}–{hi:g} m" for lo, hi in BANDS)
             + " | sky |", "|---|---|" + "---|" * (len(BANDS) + 1)]
    for name in names:
        preset = load_preset(name)
        runs = seeds if preset.heterogeneity > 0 else 1
        maps = torch.stack([opacity(pair, name, seed) for seed in range(runs)])
        values = [float(maps[:, m].mean()) for m in masks]
        vis = extinction_visibility(preset.extinction)
        lines.append(f"| `{name}` | {vis:.0f} m | "
                     + " | ".join(f"{x:.2f}" for x in values) + " |")
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(PRESETS))
    parser.add_argument("--seeds", type=int, default=4)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    for line in table(args.presets, args.seeds):
        print(line)


if __name__ == "__main__":
    main()
