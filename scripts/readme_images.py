"""Regenerate docs/images/presets.png: snow, rain, sparks and fog on the demo scene (frame 1).

The picture is tracked in git, so the script leaves it untouched when a fresh rendering differs
from it by at most one grey level per pixel (floating-point rounding across machines and library
versions moves a few pixels across a quantisation step; that is no change worth a commit). Pass
``--force`` to rewrite it anyway.
"""

import argparse
from pathlib import Path

import numpy as np
import torch

from weathergen.datasets import open_dataset
from weathergen.engine import load_preset, render_pair, sample_particles
from weathergen.io.images import read_raw, to_uint8, write_png

PICTURE = Path(__file__).resolve().parents[1] / "docs" / "images" / "presets.png"


def render_sheet() -> np.ndarray:
    """The picture as (2 * H, 2 * W, 3) uint8 RGB."""
    torch.set_num_threads(1)          # as `weathergen render`: reductions in one fixed order
    ds = open_dataset("demo", scenes=["street"], frames_per_scene=1)
    pair = ds.load(ds.pairs()[0])
    tiles = []
    for name in ("snow", "rain", "sparks", "fog"):
        # each preset as sampling scales it to the demo's 384x176 frames (count by area, sizes by
        # diagonal), as `weathergen render` does
        particles = sample_particles(pair, load_preset(name), seed=0)
        with torch.no_grad():
            img = render_pair(pair, particles).image1[0].permute(1, 2, 0).numpy()
        tiles.append(img)
    return to_uint8(np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])]))


def main(out: Path = PICTURE, force: bool = False) -> bool:
    """Write the picture to ``out``; return False when it was left as it was (no real change)."""
    sheet = render_sheet()
    if out.exists() and not force:
        old = read_raw(out)[..., ::-1]          # stored BGR
        if old.shape == sheet.shape and np.abs(old.astype(int) - sheet.astype(int)).max() <= 1:
            print(f"{out}: unchanged (within one grey level of a fresh rendering; --force rewrites it)")
            return False
    write_png(out, sheet)
    print(f"wrote {out}")
    return True


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=PICTURE, help="where to write (default: the README's picture)")
    parser.add_argument("--force", action="store_true", help="rewrite even when nothing visible changed")
    args = parser.parse_args()
    main(args.out, args.force)
