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

    python scripts/depth_completion.py
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from weathergen.datasets import demo_pairs
from weathergen.datasets.depth import complete_depth, lidar_scan
from weathergen.framepair import COMPLETED, SKY
from weathergen.geometry import backproject, invert_rigid, transform_points

#: Surfaces of the demo street above this height (metres) are the sky.
SKY_ABOVE = 3.8
FAR_DEPTH = 1000.0
NEAR_PX = 24.0


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


if __name__ == "__main__":
    main()
