"""KITTI 2015 scene-flow reader: frames 10 and 11, depth from sparse disparity, estimated camera motion.

Layout below the root (the ``data_scene_flow`` folder; ``SPLIT`` is ``training`` or ``testing``)::

    SPLIT/image_2/NNNNNN_10.png, NNNNNN_11.png   left colour frames (the pair)
    SPLIT/calib_cam_to_cam/NNNNNN.txt            P_rect_02, P_rect_03
    SPLIT/disp_occ_0/NNNNNN_10.png               disparity of frame 10 (sparse, 16-bit / 256)
    SPLIT/disp_occ_1/NNNNNN_10.png               disparity of frame 11, at the frame-10 pixels
    SPLIT/flow_occ/NNNNNN_10.png                 flow 10 -> 11 (sparse, 16-bit u, v, valid)
    SPLIT/obj_map/NNNNNN_10.png                  optional: 0 = static background, 1, 2, ... moving
    SPLIT/disp_occ_0/NNNNNN_11.png               optional: disparity of frame 11 at its own pixels

A pair is identified as scene ``NNNNNN``, frame 10.

Depth. ``depth = fx * B / disparity`` with ``fx`` from ``P_rect_02`` and the baseline ``B`` from
``P_rect_02`` and ``P_rect_03`` (metres). KITTI's disparity is measured on a subset of pixels, so
it is completed (:func:`~weathergen.datasets.depth.complete_depth`): the sky is estimated
(KITTI labels none) and gets ``far_depth``; gaps within ``max_gap_px`` of a measurement are filled
by an edge-aware interpolation guided by the frame, and larger regions (everything above the
laser scanner's field of view that is not sky) by extending each column's top-most value upward;
``depth_provenance1/2`` in the record say which pixel is which.

Frame-2 depth. ``disp_occ_0/NNNNNN_11.png``, where it exists (for example a stereo network's
prediction for frame 11), is frame 11's disparity at its own pixels and is used as it is.
Otherwise ``disp_occ_1`` gives frame 11's disparity *at frame-10 pixels*: the disparity the point
seen at ``p`` in frame 10 has in frame 11, where it appears at ``p + flow(p)``. We move each such
measurement to its frame-11 pixel (forward warping with the ground-truth flow, rounded to the
nearest pixel; where two land on one pixel the nearer surface wins) and fill the result guided by
frame 11, exactly as for frame 10. This uses the measurements of moving objects too, which a depth
computed from the camera-motion fit could not.

Camera motion. KITTI has no poses, so ``cam2_from_cam1`` is estimated
(:mod:`~weathergen.datasets.camera_motion`): every pixel with valid flow and frame-10 disparity
gives a 3D point in camera 10 and the pixel where it appears in frame 11, and OpenCV's robust
perspective-n-point solver (RANSAC, then Levenberg-Marquardt on the inliers' reprojection error)
finds the motion that the static scene agrees on. Moving objects are outliers; ``obj_map``, when
present, removes them beforehand (``use_object_map=False`` ignores it). Without flow (the testing
split with your own disparities), correspondences come from SIFT feature matching between the two
frames, with frame-10 depth from the densified disparity.
The record's ``meta["camera_motion"]`` reports the motion (translation, rotation angle), the
inlier fraction and the reprojection error. A pair is refused, with a message naming it and giving
these figures, when fewer than ``fit.min_points`` correspondences exist, when fewer than
``fit.min_inlier_fraction`` of them agree within ``fit.threshold_px``, or when the inliers' RMS
error exceeds ``fit.max_rms_px`` (:class:`~weathergen.datasets.camera_motion.FitSettings`).
There is no world frame: ``cam1_from_world`` and ``cam2_from_world`` are None.

Testing split. It ships only frames and calibration: no disparity, flow or object map, so there is
no depth and loading a testing pair fails with a message saying so, naming the two files that
would make it readable (listing and ``check`` work). Put disparities of your own (a stereo
network's) as ``disp_occ_0/NNNNNN_10.png`` and ``disp_occ_0/NNNNNN_11.png`` to render weather
into it; the same frame-11 file stands in for a training pair's missing ``disp_occ_1`` and flow.
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch

from ..errors import ConfigError, DatasetError
from ..framepair import COMPLETED, FramePair, PairId
from ..io.kitti_formats import read_disparity_png, read_flow_png, read_object_map, stereo_camera
from .base import NativeFlow, PairRef, Selection
from .camera_motion import (FitSettings, MotionFit, backproject_pixels, check_fit, fit_motion_pnp,
                            match_features)
from .common import (FarDepthDataset, add_warnings, check_size, chw, flow_warnings,
                     provenance_meta, read_frames, require_files, scaled_motion)
from .depth import complete_depth
from .stereo import RightCamera, rectified_right

_IMAGE_RE = re.compile(r"^(\d{6})_(\d{2})\.png$")
#: KITTI 2015 gives ground truth for the pair (10, 11) only.
FIRST_FRAME = 10
#: A warped frame-2 disparity is taken as hidden when a sample within this many pixels has a
#: disparity larger by more than 1 / ratio (that is, a surface at least 20 % nearer).
OCCLUSION_RADIUS = 3
OCCLUSION_RATIO = 0.8


class KittiDataset(FarDepthDataset):
    """Pairs (10, 11) of every KITTI 2015 scene-flow sequence, with densified depth and fitted motion.

    ``fit`` holds the camera-motion fit's thresholds (:class:`FitSettings`); the keyword options
    ``fit_threshold_px``, ``fit_min_points``, ``fit_min_inlier_fraction`` and ``fit_max_rms_px``
    set its fields one by one (as the command line does).
    """

    name = "kitti"
    default_world_up = "-y"          # no world frame: camera 1 is the world, and KITTI's rig is level
    split_folders = {"training": "training", "train": "training", "testing": "testing", "test": "testing"}
    #: Flow networks are evaluated on KITTI with the padding at the bottom (and split left/right).
    padding = "bottom"
    stereo = True                    # image_3, the rig's right camera
    frame_rate = 10.0                # its cameras record at 10 Hz
    native_flow = NativeFlow("flow_occ", "kitti-png")
    options = FarDepthDataset.options + (
        "max_gap_px", "fit", "fit_threshold_px", "fit_min_points", "fit_min_inlier_fraction",
        "fit_max_rms_px", "use_object_map")

    def __init__(self, root, selection: Selection = Selection(), *, max_gap_px: float = 24.0,
                 fit: Optional[FitSettings] = None, fit_threshold_px: Optional[float] = None,
                 fit_min_points: Optional[int] = None,
                 fit_min_inlier_fraction: Optional[float] = None,
                 fit_max_rms_px: Optional[float] = None, use_object_map: bool = True, **options):
        super().__init__(root, selection, **options)
        if not max_gap_px >= 0:
            raise ConfigError(f"max_gap_px must be zero or positive, got {max_gap_px}")
        fit = fit or FitSettings()
        overrides = {k: v for k, v in (("threshold_px", fit_threshold_px), ("min_points", fit_min_points),
                                        ("min_inlier_fraction", fit_min_inlier_fraction),
                                        ("max_rms_px", fit_max_rms_px)) if v is not None}
        if overrides:
            fit = replace(fit, **overrides)
        self.max_gap_px = float(max_gap_px)
        self.fit = fit
        self.use_object_map = bool(use_object_map)

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
            "disp2_own": s / "disp_occ_0" / f"{scene}_11.png",
            "flow": s / "flow_occ" / f"{scene}_10.png",
            "objects": s / "obj_map" / f"{scene}_10.png",
        }

    def needed_files(self, ref: PairRef) -> tuple[str, ...]:
        """Keys of the files this pair cannot do without (the optional ones depend on the others).

        Frame 11's own disparity (``disp2_own``) replaces ``disp_occ_1`` and the flow; on the
        testing split, which ships neither, it is what the pair needs (with frame 10's)."""
        return ("image1", "image2", "calib") + self._depth_files(ref.files)

    def _depth_files(self, files: dict) -> tuple[str, ...]:
        if Path(files["disp2_own"]).exists():
            return ("disp1",)
        return ("disp1", "disp2_own") if self.testing else ("disp1", "disp2", "flow")

    def missing_hint(self, key: str, scene: str = "NNNNNN") -> str:
        if self.testing and key in ("disp1", "disp2", "disp2_own", "flow"):
            return (f" (the KITTI testing split ships no disparity or flow, so it has no depth; use "
                    f"the training split, or put disparities of your own as "
                    f"disp_occ_0/{scene}_10.png and disp_occ_0/{scene}_11.png)")
        if key in ("disp2", "flow"):
            return (f" (without disp_occ_1 and flow_occ, frame 11's own disparity as "
                    f"disp_occ_0/{scene}_11.png lets the pair be read: frame-2 depth from it, the "
                    f"camera motion from feature matching)")
        return ""

    def right_camera(self, pair: FramePair) -> RightCamera:
        """``image_3``'s two frames, at the baseline of the calibration (``baseline_m``)."""
        root = self.split_dir / "image_3"
        files = (root / f"{pair.id.scene}_{pair.id.frame}.png",
                 root / f"{pair.id.scene}_{pair.id.frame + 1}.png")
        return rectified_right(files, float(pair.meta["baseline_m"]), pair)

    def pair_notes(self, pair: FramePair) -> list[str]:
        fit = pair.meta.get("camera_motion")
        if not fit:
            return super().pair_notes(pair)
        t = fit["translation"]
        return super().pair_notes(pair) + [
                f"camera motion t=({t[0]:+.3f}, {t[1]:+.3f}, {t[2]:+.3f}), rotation {fit['rotation_deg']:.2f}°, "
                f"{100 * fit['inlier_fraction']:.0f}% of {fit['points']} points within "
                f"{fit['threshold_px']:g} px, RMS {fit['rms_px']:.2f} px"]

    # -- reading ---------------------------------------------------------------------------------
    def load(self, ref: PairRef) -> FramePair:
        files = ref.files
        require_files(files, ("image1", "image2", "calib"))
        for key in self._depth_files(files):
            require_files(files, (key,), self.missing_hint(key, ref.id.scene))
        own2 = Path(files["disp2_own"]).exists()

        img1, img2, meta = read_frames(files)
        size = img1.shape[:2]
        check_size(files["image2"], "frame", img2.shape, size)
        k, baseline = stereo_camera(files["calib"])
        focal_baseline = k[0, 0] * baseline

        disp1, valid1 = read_disparity_png(files["disp1"])
        check_size(files["disp1"], "disparity", disp1.shape, size)
        flow = flow_valid = None
        if Path(files["flow"]).exists():
            flow, flow_valid = read_flow_png(files["flow"])
            check_size(files["flow"], "flow", flow.shape, size)
        flow, flow_valid, notes = flow_warnings(files["flow"], flow, flow_valid)
        add_warnings(meta, notes)
        objects = None
        if self.use_object_map and Path(files["objects"]).exists():
            objects = read_object_map(files["objects"])
            check_size(files["objects"], "object map", objects.shape, size)

        if own2:
            disp2, valid2 = read_disparity_png(files["disp2_own"])
            check_size(files["disp2_own"], "disparity", disp2.shape, size)
        else:
            disp2_at1, valid2_at1 = read_disparity_png(files["disp2"])
            check_size(files["disp2"], "disparity", disp2_at1.shape, size)
            disp2, valid2 = forward_warp_disparity(disp2_at1, valid2_at1 & flow_valid, flow)
        depth1, prov1 = self._dense_depth(disp1, valid1, img1, focal_baseline)
        depth2, prov2 = self._dense_depth(disp2, valid2, img2, focal_baseline)
        known1 = prov1 <= COMPLETED

        fit = self._fit_motion(ref, files, k, depth1, known1, valid1, img1, img2, flow, flow_valid,
                               objects)

        scale = self.scale_of(ref.id.scene)
        return FramePair(
            id=ref.id,
            image1=chw(img1), image2=chw(img2),
            depth1=chw(depth1 * np.float32(scale)), depth2=chw(depth2 * np.float32(scale)),
            intrinsics=torch.from_numpy(k),
            cam2_from_cam1=scaled_motion(fit.cam2_from_cam1, scale, self.keeps_translation(ref.id.scene)),
            flow=None if flow is None else chw(flow),
            flow_valid=None if flow_valid is None else chw(flow_valid),
            depth_provenance1=chw(prov1), depth_provenance2=chw(prov2),
            sources={key: Path(v) for key, v in files.items() if Path(v).exists()},
            depth_scale=scale, frame_rate=self.frame_rate,
            meta={"camera_motion": fit.summary(), "baseline_m": baseline, "far_depth": self.far_depth,
                  **meta, **provenance_meta((prov1, prov2))},
        ).validate()

    def _dense_depth(self, disparity, valid, image, focal_baseline) -> tuple[np.ndarray, np.ndarray]:
        depth = np.where(valid, focal_baseline / np.where(valid, disparity, 1.0), 0.0)
        return complete_depth(depth, valid, image, far_depth=self.far_depth,
                              max_gap_px=self.max_gap_px)

    def _fit_motion(self, ref, files, k, depth1, known1, valid1, img1, img2, flow, flow_valid,
                    objects) -> MotionFit:
        """The camera motion of a pair, from flow where it exists, else from matched features."""
        pair = f"pair {ref.id.scene} (frames 10-11)"
        if flow is not None:
            usable = valid1 & flow_valid
            if objects is not None:
                usable &= objects == 0
            ys, xs = np.nonzero(usable)
            pix1 = np.stack([xs, ys], 1).astype(np.float64)
            pix2 = pix1 + flow[ys, xs].astype(np.float64)
            z1 = depth1[ys, xs].astype(np.float64)
            source, where = "flow", files["flow"]
            count_where = files["objects"] if objects is not None else where
            what = ("static pixels (obj_map 0) with" if objects is not None else "pixels with") + \
                " flow and frame-10 disparity"
        else:
            pix1, pix2 = match_features(img1, img2)
            xi = np.clip(np.rint(pix1[:, 0]).astype(int), 0, depth1.shape[1] - 1)
            yi = np.clip(np.rint(pix1[:, 1]).astype(int), 0, depth1.shape[0] - 1)
            keep = known1[yi, xi]
            if objects is not None:
                keep &= objects[yi, xi] == 0
            pix1, pix2 = pix1[keep], pix2[keep]
            z1 = depth1[yi[keep], xi[keep]].astype(np.float64)
            source, where = "features", files["image2"]
            count_where = where
            what = "matched features (no flow_occ file) on pixels with frame-10 depth"
        n = len(pix1)
        if n < self.fit.min_points:
            raise DatasetError(f"{count_where}: camera motion of {pair}: only {n} {what}; the fit needs "
                               f"at least {self.fit.min_points}")
        fit = fit_motion_pnp(backproject_pixels(pix1, z1, k), pix2, k, self.fit, source=source)
        problem = check_fit(fit, self.fit)
        if problem:
            raise DatasetError(f"{where}: camera motion of {pair} is not trusted: {problem}")
        return fit

    def describe(self) -> dict:
        out = super().describe()
        out.update(max_gap_px=self.max_gap_px, use_object_map=self.use_object_map,
                   **self.fit.describe())
        return out


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
