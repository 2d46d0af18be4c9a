"""Readers and writers of the KITTI 2015 formats: disparity and flow PNGs, object maps, calibration.

Formats:
- **Disparity** (``disp_occ_0/NNNNNN_10.png``, ``disp_occ_1/...``): one-channel 16-bit PNG,
  disparity in pixels = value / 256; 0 marks a pixel without a measurement.
- **Flow** (``flow_occ/NNNNNN_10.png``): three-channel 16-bit PNG whose channels, in file (RGB)
  order, are ``u``, ``v`` and ``valid``; flow in pixels = (value - 2**15) / 64, valid = non-zero.
  OpenCV hands the channels over in BGR order, i.e. ``(valid, v, u)``.
- **Object map** (``obj_map/NNNNNN_10.png``): one-channel 8- or 16-bit PNG; 0 is the static
  background, 1, 2, ... number the moving objects.
- **Calibration** (``calib_cam_to_cam/NNNNNN.txt``): text lines ``KEY: v1 v2 ...``; the rectified
  projection matrices ``P_rect_02`` (left colour camera, ``image_2``) and ``P_rect_03`` (right) are
  3x4 row-major. ``P_rect_0i = K [I | t_i]`` with ``P[0, 3] = fx * t_i,x``, so the stereo baseline
  is ``(P_rect_02[0, 3] - P_rect_03[0, 3]) / fx``.

Readers return numpy arrays and raise :class:`~weathergen.errors.FormatError` naming the file.
Writers are atomic.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import FormatError
from .text import read_text_file
from .atomic import atomic_write_bytes
from .images import read_raw

_FLOW_OFFSET = 2 ** 15
_FLOW_SCALE = 64.0
_DISP_SCALE = 256.0


def _encode_png(arr: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def _read_16bit(path: Path, kind: str, channels: int) -> np.ndarray:
    raw = read_raw(path)
    if raw.dtype != np.uint16:
        raise FormatError(path, f"is a {raw.dtype} image, expected a 16-bit PNG ({kind})")
    have = 1 if raw.ndim == 2 else raw.shape[2]
    if have != channels:
        raise FormatError(path, f"has {have} channels, expected {channels} ({kind})")
    return raw


# -- disparity -----------------------------------------------------------------------------------
def read_disparity_png(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI disparity map. Shape: returns ``(disparity (H, W) float32 px, valid (H, W) bool)``."""
    path = Path(path)
    raw = _read_16bit(path, "KITTI disparity", 1)
    return raw.astype(np.float32) / np.float32(_DISP_SCALE), raw > 0


def write_disparity_png(path: str | Path, disparity: np.ndarray, valid: np.ndarray | None = None) -> Path:
    """Write a KITTI disparity map atomically.

    Shape: disparity (H, W) pixels; valid (H, W) bool (default: finite and > 0). Valid values are
    rounded to 1/256 px and kept at least 1/256 so that they stay distinguishable from "invalid".
    """
    disparity = np.asarray(disparity, np.float64)
    if disparity.ndim != 2:
        raise ValueError(f"disparity must be (H, W), got shape {disparity.shape}")
    ok = np.isfinite(disparity) & (disparity > 0)
    valid = ok if valid is None else (np.asarray(valid, bool) & ok)
    if valid.any() and disparity[valid].max() >= 65535 / _DISP_SCALE:
        raise ValueError(f"disparity {disparity[valid].max():.1f} px does not fit a KITTI PNG (max 255.99)")
    coded = np.where(valid, np.clip(np.round(np.where(valid, disparity, 0) * _DISP_SCALE), 1, 65535), 0)
    return atomic_write_bytes(path, _encode_png(coded.astype(np.uint16)))


# -- flow ----------------------------------------------------------------------------------------
def read_flow_png(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a KITTI flow map. Shape: returns ``(flow (H, W, 2) float32 px, u then v; valid (H, W) bool)``."""
    path = Path(path)
    raw = _read_16bit(path, "KITTI flow", 3)
    valid = raw[..., 0] > 0                         # BGR order: (valid, v, u)
    flow = (raw[..., [2, 1]].astype(np.float32) - _FLOW_OFFSET) / np.float32(_FLOW_SCALE)
    flow[~valid] = 0
    return flow, valid


def write_flow_png(path: str | Path, flow: np.ndarray, valid: np.ndarray | None = None) -> Path:
    """Write a KITTI flow map atomically. Shape: flow (H, W, 2) px, u then v; valid (H, W) bool.

    Values are rounded to 1/64 px; flow beyond +-512 px cannot be stored and raises ValueError.
    """
    flow = np.asarray(flow, np.float64)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got shape {flow.shape}")
    ok = np.isfinite(flow).all(axis=2)
    valid = ok if valid is None else (np.asarray(valid, bool) & ok)
    coded = np.round(np.where(valid[..., None], flow, 0) * _FLOW_SCALE) + _FLOW_OFFSET
    if coded.min() < 0 or coded.max() > 65535:
        raise ValueError("flow beyond +-512 px does not fit a KITTI flow PNG")
    bgr = np.stack([valid.astype(np.float64), coded[..., 1], coded[..., 0]], axis=2)
    return atomic_write_bytes(path, _encode_png(bgr.astype(np.uint16)))


# -- object map ----------------------------------------------------------------------------------
def read_object_map(path: str | Path) -> np.ndarray:
    """Read a KITTI object map. Shape: returns (H, W) int32, 0 = static background."""
    path = Path(path)
    raw = read_raw(path)
    if raw.ndim == 3:
        # some tools save the map as grey RGB; accept it when the channels agree
        if not (raw == raw[..., :1]).all():
            raise FormatError(path, "object map has differing colour channels, expected one channel")
        raw = raw[..., 0]
    return raw.astype(np.int32)


def write_object_map(path: str | Path, objects: np.ndarray) -> Path:
    """Write a KITTI object map (8-bit PNG) atomically. Shape: objects (H, W) ints in [0, 255]."""
    objects = np.asarray(objects)
    if objects.ndim != 2 or objects.min() < 0 or objects.max() > 255:
        raise ValueError("object map must be (H, W) with ids in [0, 255]")
    return atomic_write_bytes(path, _encode_png(objects.astype(np.uint8)))


# -- calibration ---------------------------------------------------------------------------------
def read_calibration(path: str | Path) -> dict[str, np.ndarray]:
    """Read a KITTI calibration text file into ``{key: float64 values}`` (non-numeric keys skipped)."""
    path = Path(path)
    text = read_text_file(path, "calibration")
    out = {}
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        try:
            out[key.strip()] = np.array([float(v) for v in rest.split()], np.float64)
        except ValueError:
            continue            # e.g. "calib_time: 09-Jan-2012 13:57:47"
    return out


def stereo_camera(path: str | Path) -> tuple[np.ndarray, float]:
    """Intrinsics of ``image_2`` and the stereo baseline, from a ``calib_cam_to_cam`` file.

    Returns ``(K (3, 3) float64, baseline)``; the baseline is in metres, positive.
    """
    path = Path(path)
    calib = read_calibration(path)
    mats = {}
    for key in ("P_rect_02", "P_rect_03"):
        if key not in calib:
            raise FormatError(path, f"has no {key} line (expected a KITTI calib_cam_to_cam file)")
        if calib[key].size != 12:
            raise FormatError(path, f"{key} has {calib[key].size} values, expected 12 (a 3x4 matrix)")
        mats[key] = calib[key].reshape(3, 4)
    p2, p3 = mats["P_rect_02"], mats["P_rect_03"]
    k = p2[:, :3].copy()
    if not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise FormatError(path, f"P_rect_02 has invalid focal lengths fx={k[0, 0]}, fy={k[1, 1]}")
    baseline = (p2[0, 3] - p3[0, 3]) / k[0, 0]
    if not baseline > 0:
        raise FormatError(path, f"P_rect_02 and P_rect_03 give a baseline of {baseline:.4f}, "
                                f"expected a positive distance (right camera to the right)")
    return k, float(baseline)


def write_calibration(path: str | Path, intrinsics: np.ndarray, baseline: float,
                      left_offset: float = 0.06) -> Path:
    """Write a minimal ``calib_cam_to_cam`` file atomically (``P_rect_02`` and ``P_rect_03``).

    ``left_offset``: x-offset (metres) of camera 2 from the reference camera 0, as in KITTI's rig.
    """
    k = np.asarray(intrinsics, np.float64)

    def proj(tx):
        p = np.zeros((3, 4))
        p[:, :3] = k
        p[0, 3] = k[0, 0] * tx
        return " ".join(f"{v:.12e}" for v in p.ravel())

    text = ("calib_time: 01-Jan-2000 00:00:00\n"
            f"P_rect_02: {proj(left_offset)}\n"
            f"P_rect_03: {proj(left_offset - baseline)}\n")
    return atomic_write_bytes(path, text.encode())
