"""Regenerate the README's pictures: docs/images/presets.png (snow, rain, sparks and fog on the demo
scene, frame 1) and docs/images/video-still.png (a frame of `weathergen preview --video` of a
`--sequence` render of the demo street with snow-moderate: input | weather | opacity).

The pictures are tracked in git, so the script leaves each untouched when a fresh rendering differs
from it by at most one grey level per pixel (floating-point rounding across machines and library
versions moves a few pixels across a quantisation step; that is no change worth a commit). Pass
``--force`` to rewrite it anyway.
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from weathergen.datasets import open_dataset
from weathergen.engine import load_preset, render_pair, sample_particles
from weathergen.io.images import read_raw, to_uint8, write_png
from weathergen.render import video_preview

IMAGES = Path(__file__).resolve().parents[1] / "docs" / "images"
PICTURE = IMAGES / "presets.png"
VIDEO_STILL = IMAGES / "video-still.png"


def render_sheet() -> np.ndarray:
    """The picture as (2 * H, 2 * W, 3) uint8 RGB."""
    torch.set_num_threads(1)          # as `weathergen render`: reductions in one fixed order
    ds = open_dataset("demo", scenes=["street"], frames_per_scene=1)
    pair = ds.load(ds.pairs()[0])
    tiles = []
    for name in ("snow", "rain", "sparks", "fog"):
        # each preset as sampling gives it the demo's 384x176 frames (its count scaled by area,
        # sizes in pixels), as `weathergen render` does
        particles = sample_particles(pair, load_preset(name), seed=0)
        with torch.no_grad():
            img = render_pair(pair, particles).image1[0].permute(1, 2, 0).numpy()
        tiles.append(img)
    return to_uint8(np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])]))


def render_video_still() -> np.ndarray:
    """The second frame of the video preview, as (H, 3 * W, 3) uint8 RGB."""
    from weathergen.cli.main import cli

    torch.set_num_threads(1)          # the opacity is re-rendered here, as the render draws it
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "snow"
        cli.main(["render", "--out", str(out), "--sequence", "--scenes", "street", "--preset",
                  "snow-moderate", "--quiet"], standalone_mode=False)
        plan = video_preview(out, with_input=True, with_opacity=True)
        frames = plan.frames()
        next(frames)
        return next(frames)


def save(out: Path, picture: np.ndarray, force: bool = False) -> bool:
    """Write ``picture`` to ``out``, unless the file there differs from it by at most one grey level
    per pixel (and not ``force``); return whether it was written."""
    if out.exists() and not force:
        old = read_raw(out)[..., ::-1]          # stored BGR
        if old.shape == picture.shape and np.abs(old.astype(int) - picture.astype(int)).max() <= 1:
            print(f"{out}: unchanged (within one grey level of a fresh rendering; --force rewrites it)")
            return False
    write_png(out, picture)
    print(f"wrote {out}")
    return True


def main(out: Path = PICTURE, force: bool = False) -> bool:
    """Write the presets picture to ``out``; return False when it was left as it was."""
    return save(out, render_sheet(), force)


def main_video_still(out: Path = VIDEO_STILL, force: bool = False) -> bool:
    """Write the video still to ``out``; return False when it was left as it was."""
    return save(out, render_video_still(), force)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--force", action="store_true", help="rewrite even when nothing visible changed")
    args = parser.parse_args()
    main(force=args.force)
    main_video_still(force=args.force)
