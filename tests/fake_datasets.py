"""Tiny KITTI, Spring and custom trees written from the demo scene's exact geometry.

The demo scene is static and ray-cast, so its depth, cameras and flow are exact: whatever the
readers get back can be compared with the truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from weathergen.geometry import backproject, transform_points

KITTI_BASELINE = 0.54


def demo_sequence(scene: str = "street"):
    """Frames of one demo scene: list of dicts with image (H, W, 3), depth (H, W), cam (4, 4), and
    the pairs (with flow). Cached per scene for the test session."""
    if scene not in _SEQ:
        from weathergen.datasets import demo_pairs

        pairs = demo_pairs(scenes=[scene])
        frames = []
        for i, p in enumerate(pairs):
            frames.append({"image": p.image1.permute(1, 2, 0).numpy(), "depth": p.depth1[0].numpy(),
                           "cam": p.cam1_from_world.numpy()})
            if i == len(pairs) - 1:
                frames.append({"image": p.image2.permute(1, 2, 0).numpy(), "depth": p.depth2[0].numpy(),
                               "cam": p.cam2_from_world.numpy()})
        _SEQ[scene] = (frames, pairs)
    return _SEQ[scene]


_SEQ: dict = {}


def frame2_disparity_at_frame1(pair, baseline: float = KITTI_BASELINE) -> np.ndarray:
    """KITTI's ``disp_occ_1``: the frame-2 disparity of the point seen at each frame-1 pixel."""
    pts = backproject(pair.depth1.double(), pair.intrinsics)              # (3, H, W)
    moved = transform_points(pair.cam2_from_cam1, pts.flatten(1).T)       # (HW, 3)
    z2 = moved[:, 2].reshape(pair.depth1.shape[1:]).numpy()
    return pair.intrinsics[0, 0].item() * baseline / z2


def write_fake_kitti(root: Path, pair, *, scene: str = "000000", density: float = 0.5,
                     sky_rows: int = 30, object_box=(100, 60, 160, 110),
                     object_motion=(6.0, -3.0), corrupt: float = 0.0,
                     seed: int = 0, split: str = "training") -> Path:
    """One KITTI 2015 pair from a demo pair; returns the split folder.

    ``density`` of the pixels below ``sky_rows`` carry disparity; the ``object_box``
    (x0, y0, x1, y1) is labelled object 1 and its flow is shifted by ``object_motion``, making it
    inconsistent with the camera motion (a moving car); ``corrupt`` of the background
    correspondences get wrong flow.
    """
    from weathergen.io.images import write_png
    from weathergen.io.kitti_formats import (write_calibration, write_disparity_png, write_flow_png,
                                             write_object_map)

    rng = np.random.default_rng(seed)
    s = Path(root) / split
    k = pair.intrinsics.numpy()
    h, w = pair.size
    fb = k[0, 0] * KITTI_BASELINE
    measured = rng.random((h, w)) < density
    measured[:sky_rows] = False

    flow = pair.flow.permute(1, 2, 0).numpy().astype(np.float64).copy()
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1)
    target = grid + flow
    inside = (target[..., 0] > -0.5) & (target[..., 0] < w - 0.5) & (target[..., 1] > -0.5) & (target[..., 1] < h - 0.5)

    objects = np.zeros((h, w), np.uint8)
    x0, y0, x1, y1 = object_box
    objects[y0:y1, x0:x1] = 1
    flow[y0:y1, x0:x1] += object_motion         # the "car" moves on its own
    if corrupt:
        bad = (rng.random((h, w)) < corrupt) & (objects == 0)
        flow[bad] += rng.uniform(4, 15, (int(bad.sum()), 2)) * rng.choice([-1, 1], (int(bad.sum()), 2))

    write_png(s / "image_2" / f"{scene}_10.png", pair.image1.permute(1, 2, 0).numpy())
    write_png(s / "image_2" / f"{scene}_11.png", pair.image2.permute(1, 2, 0).numpy())
    write_calibration(s / "calib_cam_to_cam" / f"{scene}.txt", k, KITTI_BASELINE)
    if split == "training":
        write_disparity_png(s / "disp_occ_0" / f"{scene}_10.png", fb / pair.depth1[0].numpy(), measured)
        write_disparity_png(s / "disp_occ_1" / f"{scene}_10.png", frame2_disparity_at_frame1(pair),
                            measured & inside)
        write_flow_png(s / "flow_occ" / f"{scene}_10.png", flow, inside)
        write_object_map(s / "obj_map" / f"{scene}_10.png", objects)
    return s


def write_fake_spring(root: Path, frames, *, scene: str = "0001", gt_factor: int = 2,
                      pairs=None, holes: float = 0.0, outliers: float = 0.0, seed: int = 0,
                      baseline: float = 0.065) -> Path:
    """A Spring scene from demo frames; ground truth at ``gt_factor`` x the frame resolution.

    At 2x, each pixel's four samples repeat its value, except that ``holes`` of the samples are NaN
    and ``outliers`` are replaced by wild values (at most one per block each), which a careful 2x2
    reduction must ignore. Flow (from ``pairs``) is written the same way.
    """
    from weathergen.io.images import write_png
    from weathergen.io.spring_formats import (write_dsp5, write_extrinsics_txt, write_flo5,
                                              write_intrinsics_txt)

    from weathergen.datasets.demo import intrinsics

    rng = np.random.default_rng(seed)
    s = Path(root) / "train" / scene
    k = intrinsics()
    for i, fr in enumerate(frames, start=1):
        write_png(s / "frame_left" / f"frame_left_{i:04d}.png", fr["image"])
        disp = k[0, 0] * baseline / fr["depth"]
        write_dsp5(s / "disp1_left" / f"disp1_left_{i:04d}.dsp5", _upsample(disp, gt_factor, holes, outliers, rng))
    write_intrinsics_txt(s / "cam_data" / "intrinsics.txt",
                         np.tile([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], (len(frames), 1)))
    write_extrinsics_txt(s / "cam_data" / "extrinsics.txt", np.stack([fr["cam"] for fr in frames]))
    for i, p in enumerate(pairs or [], start=1):
        write_flo5(s / "flow_FW_left" / f"flow_FW_left_{i:04d}.flo5",
                   _upsample(p.flow.permute(1, 2, 0).numpy(), gt_factor, holes, outliers, rng))
    return Path(root)


def _upsample(a: np.ndarray, factor: int, holes: float, outliers: float, rng) -> np.ndarray:
    """Repeat every pixel ``factor`` x ``factor`` times; damage one sample of some 2x2 blocks."""
    out = np.repeat(np.repeat(a, factor, axis=0), factor, axis=1).astype(np.float32)
    if factor != 2:
        return out
    h, w = a.shape[:2]
    for frac, value in ((holes, np.nan), (outliers, 1e4)):
        if frac:
            blocks = rng.random((h, w)) < frac
            ys, xs = np.nonzero(blocks)
            dy, dx = rng.integers(0, 2, len(ys)), rng.integers(0, 2, len(ys))
            # at most one hole and one outlier per block: two intact samples always outvote them
            sel = (2 * ys + dy, 2 * xs + dx)
            out[sel] = value
    return out


def write_fake_custom(root: Path, frames, *, depth_suffix: str = ".npy", pose: str = "cam_from_world",
                      axes: str = "opencv", depth_kind: str = "z", text: bool = False,
                      png_scale: float = 0.001, missing: tuple = (), stem=None,
                      stem_keys: bool = False, flows=None) -> Path:
    """A custom-layout scene at ``root`` from demo frames (cameras converted to the asked conventions).

    ``missing``: (row0, row1) band of frame 0 written as missing depth (0). ``stem(i)`` names frame
    ``i`` (default ``0000``...); ``stem_keys`` keys the camera file by stems instead of numbers;
    ``flows``: the demo pairs, whose flow is written as ``flow/STEM.flo``."""
    from weathergen.io.sintel_formats import write_flo

    stem = stem or (lambda i: f"{i:04d}")
    from weathergen.datasets.demo import intrinsics
    from weathergen.geometry import invert_rigid
    from weathergen.io.custom_formats import write_camera_json, write_camera_txt, write_depth
    from weathergen.io.images import write_png

    root = Path(root)
    k = intrinsics()
    gl_from_cv = np.diag([1.0, -1.0, -1.0, 1.0])
    poses = {}
    for i, fr in enumerate(frames):
        write_png(root / "frames" / f"{stem(i)}.png", fr["image"])
        if flows is not None and i < len(flows):
            write_flo(root / "flow" / f"{stem(i)}.flo", flows[i].flow.permute(1, 2, 0).numpy())
        depth = fr["depth"].copy()
        if depth_kind == "range":
            rays = backproject(torch.ones(1, *depth.shape, dtype=torch.float64), torch.from_numpy(k)).numpy()
            depth = depth * np.linalg.norm(rays, axis=0)
        if i == 0 and missing:
            depth[missing[0]:missing[1]] = 0
        write_depth(root / "depth" / f"{stem(i)}{depth_suffix}", depth, png_scale if depth_suffix == ".png" else None)
        cam = fr["cam"]
        if axes == "opengl":
            cam = gl_from_cv @ cam
        if pose == "world_from_cam":
            cam = invert_rigid(torch.from_numpy(cam)).numpy()
        poses[stem(i) if stem_keys else i] = cam
    settings = dict(pose=pose, axes=axes, depth=depth_kind)
    if depth_suffix == ".png":
        settings["depth_png_scale"] = png_scale
    if text:
        write_camera_txt(root / "cameras.txt", poses, k, **settings)
    else:
        write_camera_json(root / "cameras.json", poses, k, **settings)
    return root


def rigid(yaw_deg: float = 0.0, pitch_deg: float = 0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A (4, 4) camera motion: yaw about camera y, then pitch about camera x, then translation ``t``."""
    a, b = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    yaw = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    pitch = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    out = np.eye(4)
    out[:3, :3] = pitch @ yaw
    out[:3, 3] = t
    return out


def write_moving_kitti(root: Path, pair, cam2_from_cam1: np.ndarray, *, moving_fraction: float = 0.3,
                       object_motion: np.ndarray = None, scene: str = "000000", density: float = 0.6,
                       sky_rows: int = 30, seed: int = 0, noise_px: float = 0.0) -> tuple[Path, np.ndarray]:
    """A KITTI pair with a known ego-motion and a rigid object covering ``moving_fraction`` of the
    measured pixels, which moves on its own by ``object_motion`` (in camera-1 coordinates).

    The demo pair gives frame 1 (image, depth) and intrinsics; flow and frame-2 disparity follow
    exactly from the chosen motions (the images of frame 2 are the demo's: the flow-based fit never
    looks at them). ``noise_px`` adds Gaussian noise of that standard deviation to the disparities
    and flow components, as measured data has. Returns ``(split folder, moving (H, W) bool)``.
    """
    from weathergen.io.images import write_png
    from weathergen.io.kitti_formats import (write_calibration, write_disparity_png, write_flow_png,
                                             write_object_map)

    rng = np.random.default_rng(seed)
    s = Path(root) / "training"
    k = pair.intrinsics.numpy()
    h, w = pair.size
    fb = k[0, 0] * KITTI_BASELINE
    measured = rng.random((h, w)) < density
    measured[:sky_rows] = False
    # the object: the columns from the left edge on that hold moving_fraction of the measurements
    per_column = np.cumsum(measured.sum(0)) / measured.sum()
    x1 = int(np.searchsorted(per_column, moving_fraction)) + 1
    moving = np.zeros((h, w), bool)
    moving[sky_rows:, :x1] = True
    obj = rigid(0.0, 0.0, (0.6, 0.0, 0.5)) if object_motion is None else object_motion

    pts = backproject(pair.depth1.double(), pair.intrinsics).flatten(1).T.numpy()      # (HW, 3)
    own = np.where(moving.reshape(-1, 1), pts @ obj[:3, :3].T + obj[:3, 3], pts)
    moved = own @ cam2_from_cam1[:3, :3].T + cam2_from_cam1[:3, 3]
    z2 = moved[:, 2]
    safe = np.where(z2 > 1e-6, z2, 1.0)
    u = k[0, 0] * moved[:, 0] / safe + k[0, 2]
    v = k[1, 1] * moved[:, 1] / safe + k[1, 2]
    grid = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2)
    flow = np.stack([u, v], 1) - grid
    ok = (z2 > 0.1) & (u > -0.5) & (u < w - 0.5) & (v > -0.5) & (v < h - 0.5) & (np.abs(flow) < 500).all(1)
    flow = np.where(ok[:, None], flow, 0).reshape(h, w, 2)
    ok = ok.reshape(h, w)

    disp1 = fb / pair.depth1[0].numpy().astype(np.float64)
    disp2 = (fb / safe).reshape(h, w)
    if noise_px:
        disp1 = np.maximum(disp1 + rng.normal(0, noise_px, disp1.shape), 0.5)
        disp2 = np.maximum(disp2 + rng.normal(0, noise_px, disp2.shape), 0.5)
        flow = flow + rng.normal(0, noise_px, flow.shape)
    write_png(s / "image_2" / f"{scene}_10.png", pair.image1.permute(1, 2, 0).numpy())
    write_png(s / "image_2" / f"{scene}_11.png", pair.image2.permute(1, 2, 0).numpy())
    write_calibration(s / "calib_cam_to_cam" / f"{scene}.txt", k, KITTI_BASELINE)
    write_disparity_png(s / "disp_occ_0" / f"{scene}_10.png", disp1, measured)
    write_disparity_png(s / "disp_occ_1" / f"{scene}_10.png", disp2, measured & ok)
    write_flow_png(s / "flow_occ" / f"{scene}_10.png", flow, ok)
    write_object_map(s / "obj_map" / f"{scene}_10.png", moving.astype(np.uint8))
    return s, moving & measured & ok


def write_fake_kitti_stereo(root: Path, pair, *, scene: str = "000004") -> Path:
    """:func:`write_fake_kitti` with a right camera: ``image_3`` holds copies of ``image_2``'s
    two frames (their content does not matter to the tests that use it). Returns the split."""
    import shutil

    split = write_fake_kitti(root, pair, scene=scene)
    (split / "image_3").mkdir()
    for n in (10, 11):
        shutil.copy(split / "image_2" / f"{scene}_{n}.png", split / "image_3" / f"{scene}_{n}.png")
    return split


class DemoKillingItsWorker:
    """Stands in for a dataset: the demo scene, whose pairs in ``deadly`` kill the worker process
    loading them with SIGKILL, as the system's out-of-memory killer would (in the main process
    they load as usual). Picklable, so that ``render --workers`` hands it to its workers."""

    def __init__(self, deadly=(), **selection):
        from weathergen.datasets import open_dataset

        self.inner = open_dataset("demo", **selection)
        self.deadly = set(deadly)

    def __getattr__(self, name):
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def load(self, ref):
        import multiprocessing
        import os
        import signal

        if ref.id.key in self.deadly and multiprocessing.parent_process() is not None:
            os.kill(os.getpid(), signal.SIGKILL)
        return self.inner.load(ref)
