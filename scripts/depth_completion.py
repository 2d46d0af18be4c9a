"""Depth completion and the sky estimate measured against exact depth (the numbers of
docs/datasets.md, "Depth with holes").

The demo street is given a sky: every surface above ``SKY_ABOVE`` metres (the walls' upper parts
and the ceiling; the boxes are lower) is replaced by a smooth bright sky at the far depth. A
LiDAR-like scan (:func:`weathergen.datasets.depth.lidar_scan`: 64 beams from +2° to −24.9°, a
sample every 4 px, 10 % lost, no return from the sky) measures the rest. Each frame is then
completed as a reader does (:func:`~weathergen.datasets.depth.complete_depth`, the sky estimated)
and compared with the exact depth: the relative error of completed pixels within 24 px of a
measurement and beyond, the completed pixels that fall in the sky, the sky estimate's recall and
precision, and the time per frame.

The look: fog-moderate drawn into the street with its depth from the scan, completed (now) or
as readers gave it before (gaps within 24 px filled, everything else at the far depth), and
from the exact depth with holes punched into it. Two figures (:func:`fog_figures`): the share of
pixels where the image has no edge (luminance gradient below :data:`WEAK_IMAGE`) but the fog's
opacity has one (gradient above :data:`STRONG_OPACITY`), and the share of white (opacity above
:data:`WHITE`) among the pixels above the top beam, to compare with the sky's share there.

    python scripts/depth_completion.py
"""

from __future__ import annotations

import time

import dataclasses

import cv2
import numpy as np
import torch

from weathergen.datasets import demo_pairs, open_dataset
from weathergen.datasets.densify import fill_sparse
from weathergen.datasets.depth import complete_depth, lidar_scan
from weathergen.engine import load_preset, render_pair
from weathergen.framepair import COMPLETED, SKY
from weathergen.geometry import backproject, invert_rigid, transform_points
from weathergen.jobs import pair_particles

#: Surfaces of the demo street above this height (metres) are the sky.
SKY_ABOVE = 3.8
FAR_DEPTH = 1000.0
NEAR_PX = 24.0
#: The fog figures' thresholds: a weak image gradient and a strong opacity gradient (per pixel,
#: Sobel / 8 of luminance and of opacity), and the opacity counted as white.
WEAK_IMAGE = 0.01
STRONG_OPACITY = 0.05
WHITE = 0.95


def street_with_sky(pair, frame: int = 1):
    """Frame ``frame`` of a demo street pair with a sky: ``(image (H, W, 3), exact depth (H, W)
    with the sky at the far depth, sky (H, W) bool)``."""
    depth = (pair.depth1 if frame == 1 else pair.depth2).double()
    cam = pair.cam1_from_world if frame == 1 else pair.cam2_from_world
    points = transform_points(invert_rigid(cam), backproject(depth, pair.intrinsics)
                              .reshape(3, -1).T)
    sky = (points[:, 2] > SKY_ABOVE).reshape(pair.size).numpy()
    image = (pair.image1 if frame == 1 else pair.image2).permute(1, 2, 0).numpy().copy()
    h, w = sky.shape
    rows = np.linspace(0, 1, h, dtype=np.float32)[:, None, None]
    blue = np.array([0.62, 0.74, 0.92], np.float32) * (1 - rows) + np.array(
        [0.86, 0.90, 0.95], np.float32) * rows
    image = np.where(sky[..., None], np.broadcast_to(blue, (h, w, 3)), image)
    exact = np.where(sky, FAR_DEPTH, depth[0].numpy()).astype(np.float32)
    return image.astype(np.float32), exact, sky


def lidar_frames(pairs=None, seed: int = 0):
    """Every frame of the demo street with a sky and its LiDAR-like scan: a list of ``(image,
    exact depth, sky, measured)``."""
    pairs = pairs or demo_pairs(scenes=("street",))
    out = []
    for i, pair in enumerate(pairs):
        for frame in (1, 2):
            image, exact, sky = street_with_sky(pair, frame)
            scan = lidar_scan(exact.shape, pair.intrinsics.numpy(), seed=seed + 2 * i + frame)
            out.append((image, exact, sky, scan & ~sky))
    return out


def measure(frames) -> dict:
    """The figures over ``frames`` (from :func:`lidar_frames`)."""
    near, far, in_sky, hits, est, truth, seconds = [], [], 0, 0, 0, 0, 0.0
    for image, exact, sky, measured in frames:
        start = time.perf_counter()
        depth, prov = complete_depth(exact, measured, image, far_depth=FAR_DEPTH)
        seconds += time.perf_counter() - start
        gap = cv2.distanceTransform((~measured).astype(np.uint8), cv2.DIST_L2, 5)
        done = prov == COMPLETED
        rel = np.abs(depth - exact) / exact
        near.append(rel[done & ~sky & (gap <= NEAR_PX)])
        far.append(rel[done & ~sky & (gap > NEAR_PX)])
        in_sky += int((done & sky).sum())
        hits += int(((prov == SKY) & sky).sum())
        est += int((prov == SKY).sum())
        truth += int(sky.sum())
    near, far = np.concatenate(near), np.concatenate(far)

    def stats(a):
        return {"pixels": int(a.size), "median": float(np.median(a)), "mean": float(a.mean()),
                "p90": float(np.quantile(a, 0.9))}

    return {"near": stats(near), "beyond": stats(far), "completed_in_sky": in_sky,
            "sky_recall": hits / max(truth, 1), "sky_precision": hits / max(est, 1),
            "ms_per_frame": 1000 * seconds / len(frames)}


def depth_before(exact, measured, image) -> np.ndarray:
    """The depth readers gave before: gaps within 24 px filled, every other pixel far."""
    inverse = np.where(measured, 1.0 / exact, 0.0).astype(np.float32)
    values, known = fill_sparse(inverse, measured, image, max_gap_px=NEAR_PX)
    return np.where(known, 1.0 / np.where(known, values, 1.0), FAR_DEPTH).astype(np.float32)


def punched(exact, sky, seed: int = 0, holes: int = 12) -> np.ndarray:
    """The exact depth's measured pixels with ``holes`` rectangles (20-60 by 10-30 px) taken out
    and no return from the sky. Shape: (H, W) bool."""
    rng = np.random.default_rng(seed)
    measured = ~sky
    h, w = sky.shape
    for _ in range(holes):
        hw, hh = int(rng.integers(20, 60)), int(rng.integers(10, 30))
        x, y = int(rng.integers(0, w - hw)), int(rng.integers(0, h - hh))
        measured[y:y + hh, x:x + hw] = False
    return measured


def fog_render(pair, image, depth, preset: str = "fog-moderate", dataset=None):
    """Frame 1 of ``pair`` with its image and depth replaced, drawn with ``preset`` as ``render``
    does (``dataset``: its reader, the demo's by default): ``(frame (H, W, 3), opacity (H, W))``."""
    ds = dataset or open_dataset("demo")
    chw = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1)))
    pair = dataclasses.replace(pair, image1=chw, depth1=torch.from_numpy(depth)[None])
    particles = pair_particles(pair, load_preset(preset), 0, world_up=ds.world_up,
                               frame_rate=ds.frame_rate)
    with torch.no_grad():
        out = render_pair(pair, particles)
    return out.image1[0].permute(1, 2, 0).numpy(), out.opacity1[0, 0].numpy()


def fog_opacity(pair, image, depth, preset: str = "fog-moderate") -> np.ndarray:
    """The opacity of ``preset`` in frame 1 of ``pair`` with its image and depth replaced."""
    return fog_render(pair, image, depth, preset)[1]


def _gradient(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a, np.float32)
    return np.hypot(cv2.Sobel(a, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(a, cv2.CV_32F, 0, 1, ksize=3)) / 8


def fog_figures(opacity, image, sky, measured) -> dict:
    """``edges``: the share of pixels with a weak image gradient and a strong opacity gradient;
    ``white_above`` and ``sky_above``: the shares of white and of sky above the top beam."""
    weak = _gradient(cv2.cvtColor(np.ascontiguousarray(image, np.float32), cv2.COLOR_RGB2GRAY)) < WEAK_IMAGE
    strong = _gradient(opacity) > STRONG_OPACITY
    above = np.arange(sky.shape[0])[:, None] < np.argmax(measured.any(axis=1))
    above = np.broadcast_to(above, sky.shape)
    return {"edges": float((weak & strong).mean()),
            "white_above": float((opacity[above] > WHITE).mean()), "sky_above": float(sky[above].mean())}


def fog_comparison(pair=None) -> dict:
    """:func:`fog_figures` of the first street pair with its LiDAR-like scan and with holes
    punched, its depth completed (``after``) or as before (``before``), and from the exact depth."""
    pair = pair or demo_pairs(scenes=("street",), frames_per_scene=1)[0]
    image, exact, sky = street_with_sky(pair)
    scan = lidar_scan(exact.shape, pair.intrinsics.numpy(), seed=1) & ~sky
    out = {"exact": fog_figures(fog_opacity(pair, image, exact), image, sky, scan)}
    for name, measured in (("lidar", scan), ("holes", punched(exact, sky))):
        after, _ = complete_depth(exact, measured, image, far_depth=FAR_DEPTH)
        for when, depth in (("before", depth_before(exact, measured, image)), ("after", after)):
            out[f"{name} {when}"] = fog_figures(fog_opacity(pair, image, depth), image, sky, scan)
    return out


def main() -> None:
    figures = measure(lidar_frames())
    for region in ("near", "beyond"):
        s = figures[region]
        print(f"{region:7s} {s['pixels']:7d} px  relative error median {s['median']:.3f}  "
              f"mean {s['mean']:.3f}  90% {s['p90']:.3f}")
    print(f"completed pixels in the sky: {figures['completed_in_sky']}")
    print(f"sky estimate: recall {figures['sky_recall']:.3f}  precision "
          f"{figures['sky_precision']:.3f}")
    print(f"{figures['ms_per_frame']:.1f} ms a frame")
    for name, f in fog_comparison().items():
        print(f"fog-moderate, {name:13s} opacity edges where the image has none "
              f"{100 * f['edges']:.2f}%, white above the top beam {100 * f['white_above']:.1f}% "
              f"(sky {100 * f['sky_above']:.1f}%)")


if __name__ == "__main__":
    main()
