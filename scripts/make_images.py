"""Regenerate every picture the documentation shows, from the bundled demo scene (``make images``).

Written into docs/images/ (``--out`` elsewhere):

- ``presets.png`` (README): snow, rain, sparks and fog on the demo street, frame 1, each panel
  labelled with its preset and particle count;
- ``video-still.png`` (docs/render.md): a frame of ``weathergen preview --video`` of a ``--sequence``
  render of the demo street with snow-moderate (input | weather | opacity);
- ``every-preset.png`` (docs/engine.md, "Pictures"): every preset, paper and field, as
  ``weathergen render --preset NAME`` draws it into frame 1 of the demo street (seed 0), one
  labelled tile each;
- ``atmosphere.png`` (docs/engine.md, "The atmosphere"): the fog ladder (mist, fog-light,
  fog-moderate, fog-heavy), heavy rain and snow and a downpour in light fog on the demo street,
  frame 1 and its opacity, after the clean frame and its depth.

- ``depth.png`` (docs/datasets.md, "Depth with holes"): the demo street given a sky and scanned
  by a LiDAR-like pattern (``scripts/depth_completion.py``): the input, where each depth comes
  from (green measured, orange completed, blue sky, red unknown), fog-moderate with the depth as
  readers gave it before (gaps within 24 px filled, the rest far) and completed.

``--real ROOT`` also draws every preset, both frames, into the first pair of a real dataset
(``--real-dataset``, KITTI layout by default; ``--depth-scale`` as for ``render``) and writes the
sheet to ``--real-out`` (default ``out/images/every-preset-real.png``), and the atmosphere's
ladder, both frames, beside it (``atmosphere-real.png``), and the depth panel of that pair
(``depth-real.png``: its reader's provenance and completed depth). These sheets show someone else's
frames: they are for looking at, not for the repository (the FlyingThings3D pair docs/engine.md
names may not be redistributed).

Everything is drawn with one torch thread and fixed seeds, so a rerun writes the same bytes. The
README's picture and the video still are tracked in git: each is left untouched when a fresh
rendering differs from it by at most one grey level per pixel (floating-point rounding across
machines moves a few pixels across a quantisation step; ``--force`` rewrites it anyway). The
sheet of every preset is stored with a palette of 256 colours (median cut, no dithering) to keep
the file small. ``--quick`` draws everything on a small crop of the demo frame (and the video
still from two pairs), for tests.
"""

from __future__ import annotations

import argparse
import dataclasses
import struct
import sys
import tempfile
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))    # depth_completion, beside this script
from depth_completion import (FAR_DEPTH, depth_before, fog_render, lidar_scan,  # noqa: E402
                              street_with_sky)

from weathergen.datasets import open_dataset
from weathergen.engine import load_preset, render_pair, sample_particles
from weathergen.engine.weather.presets import list_presets
from weathergen.errors import WeatherGenError
from weathergen.io.atomic import atomic_write_bytes
from weathergen.io.images import read_raw, to_uint8
from weathergen.render import pair_particles, video_preview

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "images"
PICTURE = IMAGES / "presets.png"
VIDEO_STILL = IMAGES / "video-still.png"
EVERY_PRESET = IMAGES / "every-preset.png"
ATMOSPHERE = IMAGES / "atmosphere.png"
DEPTH = IMAGES / "depth.png"
#: The colours of the depth provenance classes: measured, completed, sky, unknown.
PROVENANCE_COLOURS = np.array([[40, 190, 60], [240, 150, 40], [90, 150, 255], [220, 40, 40]],
                              np.uint8)
REAL_SHEET = ROOT / "out" / "images" / "every-preset-real.png"
#: The atmosphere's ladder, as ``atmosphere.png`` shows it ("clean": the frame without weather).
LADDER = ("clean", "mist", "fog-light", "fog-moderate", "fog-heavy", "rain-heavy", "snow-heavy",
          "rain-heavy+fog-light")
#: The crop of the demo frame that ``--quick`` draws on: (top, left, height, width).
QUICK_CROP = (24, 96, 128, 192)
LABEL_PX = 18                          # the label strip above each tile of a sheet


def demo_pair(quick: bool = False):
    """The first pair of the demo street (a crop of it for ``quick``) and its reader."""
    ds = open_dataset("demo", scenes=["street"], frames_per_scene=1)
    pair = ds.load(ds.pairs()[0])
    return (crop(pair, *QUICK_CROP) if quick else pair), ds


def crop(pair, top: int, left: int, height: int, width: int):
    """A window of a pair: every per-pixel tensor cut, the principal point moved with it."""
    rows, cols = slice(top, top + height), slice(left, left + width)
    cut = {f.name: getattr(pair, f.name)[..., rows, cols]
           for f in dataclasses.fields(pair)
           if isinstance(getattr(pair, f.name), torch.Tensor) and getattr(pair, f.name).dim() == 3}
    k = pair.intrinsics.clone()
    k[0, 2] -= left
    k[1, 2] -= top
    return dataclasses.replace(pair, intrinsics=k, **cut)


# -- the README's picture and the video still ---------------------------------------------

def render_sheet(quick: bool = False) -> np.ndarray:
    """The README picture: the paper's four weathers in a 2 x 2 grid, each panel below a strip
    that names it (preset and particle count). Shape: (2 * (LABEL_PX + H), 2 * W, 3) uint8 RGB."""
    torch.set_num_threads(1)          # as `weathergen render`: reductions in one fixed order
    pair, _ = demo_pair(quick)
    tiles = []
    for name in ("snow", "rain", "sparks", "fog"):
        # each preset as sampling gives it the demo's 384x176 frames (its count scaled by area,
        # sizes in pixels), as `weathergen render` does
        particles = sample_particles(pair, load_preset(name), seed=0)
        with torch.no_grad():
            img = render_pair(pair, particles).image1[0].permute(1, 2, 0).numpy()
        what = "clouds" if name == "fog" else "particles"
        tiles.append(labelled(to_uint8(img), f"{name}: {len(particles)} {what}"))
    return np.vstack([np.hstack(tiles[:2]), np.hstack(tiles[2:])])


def render_video_still(quick: bool = False) -> np.ndarray:
    """The second frame of the video preview, as (H, 3 * W, 3) uint8 RGB."""
    from weathergen.cli.main import cli

    torch.set_num_threads(1)          # the opacity is re-rendered here, as the render draws it
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "snow"
        cli.main(["render", "--out", str(out), "--sequence", "--scenes", "street", "--preset",
                  "snow-moderate", "--quiet", *(["--frames-per-scene", "2"] if quick else [])],
                 standalone_mode=False)
        plan = video_preview(out, with_input=True, with_opacity=True, width=96 if quick else None)
        frames = plan.frames()
        next(frames)
        return next(frames)


# -- sheets of every preset -------------------------------------------------------------------

def preset_frames(pair, dataset, name: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Frames 1 and 2 of ``pair`` with preset ``name`` as ``weathergen render --preset NAME
    --seed SEED`` draws them (the pair's own seed, the reader's world up and frame rate), uint8."""
    particles = pair_particles(pair, load_preset(name), seed, world_up=dataset.world_up,
                               frame_rate=dataset.frame_rate)
    with torch.no_grad():
        out = render_pair(pair, particles)
    return tuple(to_uint8(img[0].permute(1, 2, 0).numpy()) for img in (out.image1, out.image2))


def sheet_order() -> list[str]:
    """Every preset, in reading order: the paper's four weathers, the paper's other rows (the
    supplement's ablations), then the weather fields, each weather light, moderate, heavy."""
    main = ["snow", "rain", "sparks", "fog"]
    paper = main + [n for n in list_presets("paper") if n not in main]
    strength = {"light": 0, "moderate": 1, "heavy": 2}
    field = sorted(list_presets("field"), key=lambda n: (main.index(n.split("-")[0])
                                                        if n.split("-")[0] in main else len(main),
                                                        strength.get(n.split("-")[-1], 3), n))
    return paper + field


def labelled(tile: np.ndarray, text: str) -> np.ndarray:
    """``tile`` below a black strip that names it."""
    strip = np.zeros((LABEL_PX, tile.shape[1], 3), np.uint8)
    scale = 0.45 if tile.shape[1] >= 160 else 0.3
    cv2.putText(strip, text, (4, LABEL_PX - 5), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255),
                1, cv2.LINE_AA)
    return np.vstack([strip, tile])


def grid(tiles: list[np.ndarray], columns: int) -> np.ndarray:
    """Tiles of one size in rows of ``columns``, the last row padded with black."""
    h, w = tiles[0].shape[:2]
    rows = -(-len(tiles) // columns)
    sheet = np.zeros((rows * h, columns * w, 3), np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = tile
    return sheet


def every_preset_sheet(pair, dataset, *, both_frames: bool = False, shrink: int = 1,
                       columns: int = 6, names=None) -> np.ndarray:
    """Every preset (paper and field; or ``names``, where ``clean`` is the frame without
    weather) drawn into ``pair``, one labelled tile each (two, frame 1 and frame 2, with
    ``both_frames``), tiles shrunk ``shrink`` times; uint8 RGB."""
    torch.set_num_threads(1)
    tiles = []
    for name in names or sheet_order():
        try:
            frames = (tuple(to_uint8(img.permute(1, 2, 0).numpy())
                            for img in (pair.image1, pair.image2)) if name == "clean"
                      else preset_frames(pair, dataset, name))
            failed = ""
        except WeatherGenError as exc:      # as `render` fails the pair: said, and shown clean
            print(f"{name}: {exc}", file=sys.stderr)
            frames = tuple(to_uint8(img.permute(1, 2, 0).numpy()) for img in (pair.image1, pair.image2))
            failed = " (failed)"
        for t, frame in enumerate(frames if both_frames else frames[:1]):
            if shrink > 1:
                frame = cv2.resize(frame, (frame.shape[1] // shrink, frame.shape[0] // shrink),
                                   interpolation=cv2.INTER_AREA)
            tiles.append(labelled(frame, (f"{name}, frame {t + 1}" if both_frames else name) + failed))
    return grid(tiles, columns)


# -- small PNGs ---------------------------------------------------------------------------------

def median_cut(pixels: np.ndarray, colours: int = 256) -> np.ndarray:
    """A palette for ``pixels`` (N, 3): the box of colours with the widest range is split at its
    median along that channel until there are ``colours`` boxes; each box's mean colour. Sorting is
    stable, so the palette is the same on every run. Returns (colours, 3) uint8."""
    boxes = [pixels.astype(np.int32)]
    while len(boxes) < colours:
        ranges = [int((b.max(0) - b.min(0)).max()) if len(b) > 1 else 0 for b in boxes]
        i = int(np.argmax(ranges))
        if ranges[i] == 0:
            break
        box = boxes.pop(i)
        channel = int(np.argmax(box.max(0) - box.min(0)))
        order = np.argsort(box[:, channel], kind="stable")
        half = len(box) // 2
        boxes += [box[order[:half]], box[order[half:]]]
    return np.array([np.round(b.mean(0)) for b in boxes], np.uint8)


def palette_png(rgb: np.ndarray, colours: int = 256) -> bytes:
    """``rgb`` (H, W, 3) uint8 as an 8-bit palette PNG: a median-cut palette of a seventh of the
    pixels, each pixel its nearest palette colour (looked up at 6 bits per channel)."""
    h, w = rgb.shape[:2]
    flat = rgb.reshape(-1, 3)
    palette = median_cut(flat[::7], colours)
    levels = np.arange(64, dtype=np.int32) * 4 + 2
    cube = np.stack(np.meshgrid(levels, levels, levels, indexing="ij"), -1).reshape(-1, 3)
    lookup = np.empty(len(cube), np.uint8)
    for start in range(0, len(cube), 8192):
        d = ((cube[start:start + 8192, None, :] - palette[None].astype(np.int32)) ** 2).sum(-1)
        lookup[start:start + 8192] = d.argmin(1)
    q = (flat >> 2).astype(np.int32)
    index = lookup[(q[:, 0] << 12) | (q[:, 1] << 6) | q[:, 2]].reshape(h, w)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    rows = b"".join(b"\x00" + index[r].tobytes() for r in range(h))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 3, 0, 0, 0))
            + chunk(b"PLTE", palette.tobytes()) + chunk(b"IDAT", zlib.compress(rows, 9))
            + chunk(b"IEND", b""))


# -- writing ----------------------------------------------------------------------------------

def save(out: Path, picture: np.ndarray, force: bool = False) -> bool:
    """Write ``picture`` to ``out``, unless the file there differs from it by at most one grey level
    per pixel (and not ``force``); return whether it was written."""
    if out.exists() and not force:
        old = read_raw(out)[..., ::-1]          # stored BGR
        if old.shape == picture.shape and np.abs(old.astype(int) - picture.astype(int)).max() <= 1:
            print(f"{out}: unchanged (within one grey level of a fresh rendering; --force rewrites it)")
            return False
    write_small_png(out, picture)
    print(f"wrote {out}")
    return True


def write_small_png(out: Path, picture: np.ndarray) -> Path:
    """``picture`` (H, W, 3) uint8 RGB as a PNG at zlib's strongest compression (lossless)."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(picture[..., ::-1]),
                           [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise RuntimeError(f"{out}: PNG encoding failed")
    out.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_bytes(out, buf.tobytes())


def save_palette(out: Path, picture: np.ndarray) -> bool:
    """Write ``picture`` as a palette PNG, unless the file holds those bytes already."""
    data = palette_png(picture)
    if out.exists() and out.read_bytes() == data:
        print(f"{out}: unchanged")
        return False
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, data)
    print(f"wrote {out} ({len(data) // 1024} KiB)")
    return True


def main(out: Path = PICTURE, force: bool = False, quick: bool = False) -> bool:
    """Write the presets picture to ``out``; return False when it was left as it was."""
    return save(out, render_sheet(quick), force)


def main_video_still(out: Path = VIDEO_STILL, force: bool = False, quick: bool = False) -> bool:
    """Write the video still to ``out``; return False when it was left as it was."""
    return save(out, render_video_still(quick), force)


def main_every_preset(out: Path = EVERY_PRESET, quick: bool = False) -> bool:
    """Write the sheet of every preset on the demo street to ``out``."""
    pair, ds = demo_pair(quick)
    return save_palette(out, every_preset_sheet(pair, ds))


def ladder_sheet(pair, dataset, *, both_frames: bool = False, shrink: int = 1) -> np.ndarray:
    """The atmosphere's ladder (:data:`LADDER`) drawn into ``pair``: per rung its frame 1 (and
    frame 2 with ``both_frames``) and the opacity of frame 1 (white: opaque), labelled; the
    ``clean`` rung shows the frame and the scene's depth instead (white: near, black: the
    farthest, at most 100 m). Four tiles a row; uint8 RGB."""
    torch.set_num_threads(1)
    tiles = []
    for name in LADDER:
        if name == "clean":
            frames = (pair.image1, pair.image2)
            depth = pair.depth1[0].double().clamp(max=100.0)
            extra, what = 1 - depth / float(depth.max()), f"depth, black {float(depth.max()):.0f} m"
        else:
            particles = pair_particles(pair, load_preset(name), 0, world_up=dataset.world_up,
                                       frame_rate=dataset.frame_rate)
            with torch.no_grad():
                out = render_pair(pair, particles)
            frames = (out.image1[0], out.image2[0])
            extra, what = out.opacity1[0, 0].double(), "opacity"
        shown = [(f"{name}, frame {t + 1}" if both_frames else name, frame)
                 for t, frame in enumerate(frames[:2 if both_frames else 1])]
        shown.append((f"{name}: {what}", extra[None].expand(3, -1, -1)))
        for label, image in shown:
            tile = to_uint8(image.permute(1, 2, 0).numpy())
            if shrink > 1:
                tile = cv2.resize(tile, (tile.shape[1] // shrink, tile.shape[0] // shrink),
                                  interpolation=cv2.INTER_AREA)
            tiles.append(labelled(tile, label))
    return grid(tiles, 4)


def main_atmosphere(out: Path = ATMOSPHERE, quick: bool = False) -> bool:
    """Write the atmosphere's ladder on the demo street to ``out``."""
    pair, ds = demo_pair(quick)
    return save_palette(out, ladder_sheet(pair, ds))


def depth_panel(pair, image, measured, provenance, depth, dataset=None) -> np.ndarray:
    """Input, provenance, and fog-moderate with the depth as readers gave it before and with
    ``depth`` (completed), four labelled tiles in a row. Shape: images (H, W, 3), the rest (H, W)
    -> (LABEL_PX + H, 4 W, 3) uint8."""
    torch.set_num_threads(1)
    before = depth_before(np.where(measured, depth, 1.0), measured, image)
    tiles = [labelled(to_uint8(image), "input"),
             labelled(PROVENANCE_COLOURS[provenance], "green measured, orange completed, blue sky")]
    for label, d in (("fog-moderate, before", before), ("fog-moderate, completed", depth)):
        tiles.append(labelled(to_uint8(fog_render(pair, image, d, dataset=dataset)[0]), label))
    return np.hstack(tiles)


def main_depth(out: Path = DEPTH) -> bool:
    """Write the depth panel of the demo street with a sky and a LiDAR-like scan to ``out``."""
    from weathergen.datasets.depth import complete_depth

    pair, _ = demo_pair()
    image, exact, sky = street_with_sky(pair)
    measured = lidar_scan(exact.shape, pair.intrinsics.numpy(), seed=1) & ~sky
    depth, provenance = complete_depth(exact, measured, image, far_depth=FAR_DEPTH)
    return save_palette(out, depth_panel(pair, image, measured, provenance, depth))


def main_real(root: Path, out: Path = REAL_SHEET, dataset: str = "kitti",
              depth_scale: float | None = None) -> Path:
    """Write the sheet of every preset, both frames, on the first pair of a real dataset, and
    the atmosphere's ladder, both frames, beside it (``atmosphere-real.png``), and the depth panel of that pair
(``depth-real.png``: its reader's provenance and completed depth)."""
    ds = open_dataset(dataset, root, frames_per_scene=1,
                      **({"depth_scale": depth_scale} if depth_scale is not None else {}))
    pair = ds.load(ds.pairs()[0])
    shrink = max(1, pair.size[1] // 480)
    sheet = every_preset_sheet(pair, ds, both_frames=True, shrink=shrink, columns=4)
    write_small_png(out, sheet)
    print(f"wrote {out} ({pair.id}, {pair.size[1]}x{pair.size[0]}, tiles 1/{shrink})")
    ladder = out.with_name("atmosphere-real.png")
    write_small_png(ladder, ladder_sheet(pair, ds, both_frames=True, shrink=shrink))
    print(f"wrote {ladder}")
    if pair.depth_provenance1 is not None:
        panel = out.with_name("depth-real.png")
        provenance = pair.depth_provenance1[0].numpy()
        write_small_png(panel, depth_panel(pair, pair.image1.permute(1, 2, 0).numpy(),
                                           provenance == 0, provenance, pair.depth1[0].numpy(), ds))
        print(f"wrote {panel}")
    return out


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=IMAGES,
                        help="folder for presets.png, video-still.png, every-preset.png, "
                             "atmosphere.png, depth.png (default docs/images)")
    parser.add_argument("--force", action="store_true",
                        help="rewrite presets.png and video-still.png even when nothing visible changed")
    parser.add_argument("--quick", action="store_true",
                        help="draw on a small crop of the demo frame (for tests; not for the docs)")
    parser.add_argument("--real", type=Path, metavar="ROOT",
                        help="also draw every preset into the first pair of this dataset")
    parser.add_argument("--real-dataset", default="kitti", help="its reader (default kitti)")
    parser.add_argument("--depth-scale", type=float,
                        help="its depth scale, as render's --depth-scale (FlyingThings3D: 0.1)")
    parser.add_argument("--real-out", type=Path, default=REAL_SHEET,
                        help="where that sheet goes (default out/images/every-preset-real.png)")
    return parser.parse_args(argv)


def run(argv=None) -> None:
    args = parse_args(argv)
    if args.quick and args.out.resolve() == IMAGES.resolve():
        sys.exit("--quick draws small stand-ins: give --out a folder other than docs/images")
    start = time.process_time()
    main(args.out / PICTURE.name, args.force, args.quick)
    main_video_still(args.out / VIDEO_STILL.name, args.force, args.quick)
    main_every_preset(args.out / EVERY_PRESET.name, args.quick)
    main_atmosphere(args.out / ATMOSPHERE.name, args.quick)
    main_depth(args.out / DEPTH.name)
    if args.real is not None:
        main_real(args.real, args.real_out, args.real_dataset, args.depth_scale)
    print(f"{time.process_time() - start:.0f} s of CPU time")


if __name__ == "__main__":
    run()
