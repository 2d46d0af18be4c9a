"""Regenerate docs/images/presets.png: snow, rain, sparks and fog on the demo scene (frame 1)."""

from pathlib import Path

import numpy as np
import torch

from weathergen.datasets import open_dataset
from weathergen.engine import load_preset, render_pair, sample_particles
from weathergen.io.images import write_png


def main(out: Path = Path(__file__).resolve().parents[1] / "docs" / "images" / "presets.png"):
    ds = open_dataset("demo", scenes=["street"], frames_per_scene=1)
    pair = ds.load(ds.pairs()[0])
    tiles = []
    h, w = pair.size
    for name in ("snow", "rain", "sparks", "fog"):
        preset = load_preset(name)
        if name == "fog":
            # fog's 60 clouds are sized in pixels for Sintel's 1024x436 frames; on the smaller demo
            # frames the same count stacks them into a white-out, so keep the coverage per pixel
            preset = load_preset(name, {"count": max(1, round(preset.count * h * w / (1024 * 436)))})
        particles = sample_particles(pair, preset, seed=0)
        with torch.no_grad():
            img = render_pair(pair, particles).image1[0].permute(1, 2, 0).numpy()
        tiles.append(img)
    sheet = np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])])
    write_png(out, sheet)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
