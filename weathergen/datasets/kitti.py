"""KITTI 2015 scene-flow reader: frames 10 and 11, depth from sparse disparity, estimated camera motion.

Layout below the root (the ``data_scene_flow`` folder; ``SPLIT`` is ``training`` or ``testing``)::

    SPLIT/image_2/NNNNNN_10.png, NNNNNN_11.png   left colour frames (the pair)
    SPLIT/disp_occ_0/NNNNNN_10.png               disparity of frame 10 (sparse, 16-bit / 256)
    SPLIT/disp_occ_1/NNNNNN_10.png               disparity of frame 11, at the frame-10 pixels
    SPLIT/flow_occ/NNNNNN_10.png                 flow 10 -> 11 (sparse, 16-bit u, v, valid)
    SPLIT/obj_map/NNNNNN_10.png                  0 = static background, 1, 2, ... moving objects
    SPLIT/calib_cam_to_cam/NNNNNN.txt            P_rect_02, P_rect_03

A pair is identified as scene ``NNNNNN``, frame 10.

Depth. ``depth = fx * B / disparity`` with ``fx`` from ``P_rect_02`` and the baseline ``B`` from
``P_rect_02`` and ``P_rect_03`` (metres). KITTI's disparity is measured on a subset of pixels, so
it is filled in with an edge-aware interpolation guided by the frame
(:func:`~weathergen.datasets.densify.fill_sparse`); pixels more than ``max_gap_px`` from any
measurement (the sky, and everything above the laser scanner's field of view) get ``far_depth``.
``depth_measured1/2`` in the record mark the measured pixels.

Frame-2 depth. ``disp_occ_1`` holds frame 11's disparity *at frame-10 pixels*: the disparity the
point seen at ``p`` in frame 10 has in frame 11, where it appears at ``p + flow(p)``. We move each
such measurement to its frame-11 pixel (forward warping with the ground-truth flow, rounded to the
nearest pixel; where two land on one pixel the nearer surface wins) and fill the result guided by
frame 11, exactly as for frame 10. This uses the measurements of moving objects too, which a depth
computed from the camera-motion fit could not.

Camera motion. KITTI has no poses, so ``cam2_from_cam1`` is estimated from the static background
(``obj_map == 0``): every background pixel with valid flow and both disparities gives a 3D point in
each camera, and a robust rigid fit (RANSAC + least squares,
:func:`~weathergen.datasets.posefit.fit_camera_motion`) finds the motion. The record's
``meta["camera_motion"]`` reports the fit (inliers, RMS residual in pixels). A pair is refused, with
a one-line message, when fewer than ``min_static_points`` background points exist or fewer than
``min_inlier_fraction`` of them agree with the motion within ``fit_threshold_px``.
There is no world frame: ``cam1_from_world`` and ``cam2_from_world`` are None.

Testing split. It ships only frames and calibration: no disparity, flow or object map, so neither
depth nor camera motion exist there and loading a testing pair fails with a message saying so
(listing and ``check`` work). Weather needs the training split.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import torch

from ..errors import ConfigError, DatasetError
from ..framepair import FramePair, PairId
from ..io.images import read_image
from ..io.kitti_formats import read_disparity_png, read_flow_png, read_object_map, stereo_camera
from .base import PairRef, Selection
from .common import FarDepthDataset, check_size, chw, require_files, scaled_motion
from .densify import fill_sparse
from .posefit import fit_camera_motion

_IMAGE_RE = re.compile(r"^(\d{6})_(\d{2})\.png$")
#: KITTI 2015 gives ground truth for the pair (10, 11) only.
FIRST_FRAME = 10
#: A warped frame-2 disparity is taken as hidden when a sample within this many pixels has a
#: disparity larger by more than 1 / ratio (that is, a surface at least 20 % nearer).
OCCLUSION_RADIUS = 3
OCCLUSION_RATIO = 0.8


class KittiDataset(FarDepthDataset):
    """Pairs (10, 11) of every KITTI 2015 scene-flow sequence, with densified depth and fitted motion."""

    name = "kitti"
    default_world_up = "-y"          # no world frame: camera 1 is the world, and KITTI's rig is level
    split_folders = {"training": "training", "train": "training", "testing": "testing", "test": "testing"}

    def __init__(self, root, selection: Selection = Selection(), *, max_gap_px: float = 24.0,
                 fit_threshold_px: float = 2.0, min_static_points: int = 200,
                 min_inlier_fraction: float = 0.6, **options):
        super().__init__(root, selection, **options)
        if not max_gap_px >= 0:
            raise ConfigError(f"max_gap_px must be zero or positive, got {max_gap_px}")
        if not fit_threshold_px > 0:
            raise ConfigError(f"fit_threshold_px must be positive, got {fit_threshold_px}")
        if int(min_static_points) < 3:
            # a rigid motion needs three points; fewer would reach the fit and fail there
            raise ConfigError(f"min_static_points must be at least 3, got {min_static_points}")
        if not 0 < min_inlier_fraction <= 1:
            raise ConfigError(f"min_inlier_fraction must be in (0, 1], got {min_inlier_fraction}")
        self.max_gap_px = float(max_gap_px)
        self.fit_threshold_px = float(fit_threshold_px)
        self.min_static_points = int(min_static_points)
        self.min_inlier_fraction = float(min_inlier_fraction)

    @property
    def testing(self) -> bool:
        return self.split_folders[self.selection.split] == "testing"

    # -- listing ---------------------------------------------------------------------------------
    def _frames_by_scene(self) -> dict[str, list[int]]:
        image_dir = self.split_dir / "image_2"
        if not image_dir.is_dir():
            raise DatasetError(f"{image_dir}: no such folder (expected KITTI 2015 layout "
                               f"ROOT/{self.split_dir.name}/image_2/000000_10.png)")
        found: dict[str, list[int]] = {}
        for p in image_dir.iterdir():
            m = _IMAGE_RE.match(p.name)
            if m:
                found.setdefault(m.group(1), []).append(int(m.group(2)))
        return {s: sorted(f) for s, f in sorted(found.items())}

    def all_scenes(self) -> list[str]:
        return sorted(self._frames_by_scene())

    def pairs(self) -> list[PairRef]:
        frames = self._frames_by_scene()
        refs = []
        for scene in self.selection.pick_scenes(list(frames), self.split_dir / "image_2"):
            if FIRST_FRAME not in frames[scene]:
                continue
            # Listed even when frame 11 is missing, so that `check` names the missing file
            # instead of the sequence silently vanishing.
            if FIRST_FRAME in self.selection.pick_frames([FIRST_FRAME, FIRST_FRAME + 1]):
                refs.append(PairRef(PairId(self.name, self.split_dir.name, scene, FIRST_FRAME),
                                    self._files(scene)))
        return refs

    def _files(self, scene: str) -> dict:
        s = self.split_dir
        return {
            "image1": s / "image_2" / f"{scene}_10.png",
            "image2": s / "image_2" / f"{scene}_11.png",
            "calib": s / "calib_cam_to_cam" / f"{scene}.txt",
            "disp1": s / "disp_occ_0" / f"{scene}_10.png",
            "disp2": s / "disp_occ_1" / f"{scene}_10.png",
            "flow": s / "flow_occ" / f"{scene}_10.png",
            "objects": s / "obj_map" / f"{scene}_10.png",
        }

    # -- reading ---------------------------------------------------------------------------------
    def load(self, ref: PairRef) -> FramePair:
        files = ref.files
        require_files(files, ("image1", "image2", "calib"))
        hint = (" (the KITTI testing split ships no disparity, flow or object maps, so it has no "
                "depth and no camera motion; use the training split)") if self.testing else ""
        require_files(files, ("disp1", "disp2", "flow", "objects"), hint)

        img1, img2 = read_image(files["image1"]), read_image(files["image2"])
        size = img1.shape[:2]
        check_size(files["image2"], "frame", img2.shape, size)
        k, baseline = stereo_camera(files["calib"])
        focal_baseline = k[0, 0] * baseline

        disp1, valid1 = read_disparity_png(files["disp1"])
        check_size(files["disp1"], "disparity", disp1.shape, size)
        disp2_at1, valid2_at1 = read_disparity_png(files["disp2"])
        check_size(files["disp2"], "disparity", disp2_at1.shape, size)
        flow, flow_valid = read_flow_png(files["flow"])
        check_size(files["flow"], "flow", flow.shape, size)
        objects = read_object_map(files["objects"])
        check_size(files["objects"], "object map", objects.shape, size)

        fit = self._fit_motion(files, k, baseline, disp1, valid1, disp2_at1, valid2_at1, flow,
                               flow_valid, objects)

        disp2, valid2 = forward_warp_disparity(disp2_at1, valid2_at1 & flow_valid, flow)
        depth1 = self._dense_depth(disp1, valid1, img1, focal_baseline)
        depth2 = self._dense_depth(disp2, valid2, img2, focal_baseline)

        scale = self.scale_of(ref.id.scene)
        return FramePair(
            id=ref.id,
            image1=chw(img1), image2=chw(img2),
            depth1=chw(depth1 * np.float32(scale)), depth2=chw(depth2 * np.float32(scale)),
            intrinsics=torch.from_numpy(k),
            cam2_from_cam1=scaled_motion(fit.cam2_from_cam1, scale, self.camera_translation),
            flow=chw(flow), flow_valid=chw(flow_valid),
            depth_measured1=chw(valid1), depth_measured2=chw(valid2),
            sources={key: Path(v) for key, v in files.items()},
            depth_scale=scale,
            meta={"camera_motion": fit.summary(), "baseline_m": baseline, "far_depth": self.far_depth},
        ).validate()

    def _dense_depth(self, disparity, valid, image, focal_baseline) -> np.ndarray:
        filled, known = fill_sparse(disparity, valid, image, max_gap_px=self.max_gap_px)
        depth = np.full(disparity.shape, self.far_depth, np.float32)
        depth[known] = focal_baseline / filled[known]
        return depth

    def _fit_motion(self, files, k, baseline, disp1, valid1, disp2_at1, valid2_at1, flow, flow_valid,
                    objects):
        focal_baseline = k[0, 0] * baseline
        static = (objects == 0) & valid1 & valid2_at1 & flow_valid
        n = int(static.sum())
        if n < self.min_static_points:
            raise DatasetError(
                f"{files['objects']}: only {n} static background pixels have flow and both "
                f"disparities; the camera-motion fit needs at least {self.min_static_points}")
        ys, xs = np.nonzero(static)
        pix1 = np.stack([xs, ys], 1).astype(np.float64)
        pix2 = pix1 + flow[ys, xs].astype(np.float64)
        points1 = _backproject(pix1, focal_baseline / disp1[ys, xs].astype(np.float64), k)
        points2 = _backproject(pix2, focal_baseline / disp2_at1[ys, xs].astype(np.float64), k)
        fit = fit_camera_motion(points1, points2, k, baseline, threshold_px=self.fit_threshold_px)
        if fit.inlier_fraction < self.min_inlier_fraction:
            raise DatasetError(
                f"{files['flow']}: camera-motion fit is bad: only {100 * fit.inlier_fraction:.0f}% of "
                f"{n} static points agree with one rigid motion within {self.fit_threshold_px:g} px "
                f"(median residual {fit.median_px:.2f} px; at least "
                f"{100 * self.min_inlier_fraction:.0f}% required)")
        return fit

    def describe(self) -> dict:
        out = super().describe()
        out.update(max_gap_px=self.max_gap_px, fit_threshold_px=self.fit_threshold_px,
                   min_static_points=self.min_static_points,
                   min_inlier_fraction=self.min_inlier_fraction)
        return out


def _backproject(pixels: np.ndarray, z: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Camera points of pixels at camera-z depths. Shape: (N, 2), (N,), (3, 3) -> (N, 3)."""
    y = (pixels[:, 1] - k[1, 2]) / k[1, 1]
    x = (pixels[:, 0] - k[0, 2] - k[0, 1] * y) / k[0, 0]
    return np.stack([x * z, y * z, z], 1)


def forward_warp_disparity(disparity: np.ndarray, valid: np.ndarray,
                           flow: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move measurements given at frame-1 pixels to the frame-2 pixels the flow takes them to.

    Shape: disparity (H, W), valid (H, W) bool, flow (H, W, 2) -> ``(disparity (H, W) float32,
    valid (H, W) bool)`` at frame-2 pixels. Targets are rounded to the nearest pixel; where several
    land on one pixel the largest disparity (the nearest surface, the one frame 2 sees) wins.

    KITTI's ``occ`` ground truth includes points that frame 2 does not see (hidden behind a nearer
    surface). Such a point can land on a pixel no nearer measurement reached, so a z-buffer of
    single pixels keeps it; we drop every sample whose disparity is below ``OCCLUSION_RATIO`` times
    the largest one within ``OCCLUSION_RADIUS`` pixels, i.e. clearly behind a neighbour. Background
    samples right next to a foreground edge go too; the fill restores them from the background.
    """
    h, w = disparity.shape
    ys, xs = np.nonzero(valid)
    tx = np.rint(xs + flow[ys, xs, 0]).astype(np.int64)
    ty = np.rint(ys + flow[ys, xs, 1]).astype(np.int64)
    inside = (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)
    tx, ty, vals = tx[inside], ty[inside], disparity[ys[inside], xs[inside]].astype(np.float32)
    out = np.zeros((h, w), np.float32)
    np.maximum.at(out, (ty, tx), vals)         # a z-buffer: the nearest surface wins
    hit = np.zeros((h, w), bool)
    hit[ty, tx] = True
    size = 2 * OCCLUSION_RADIUS + 1
    nearest = cv2.dilate(out, np.ones((size, size), np.uint8))
    hit &= out >= OCCLUSION_RATIO * nearest
    out[~hit] = 0
    return out, hit
