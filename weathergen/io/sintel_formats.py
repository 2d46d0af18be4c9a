"""Readers and writers of the MPI-Sintel binary formats: ``.dpt`` depth, ``.cam`` cameras, ``.flo`` flow.

Formats (all little-endian):
- ``.dpt``: float32 tag 202021.25, int32 width, int32 height, then width*height float32 depths,
  row-major.
- ``.cam``: float32 tag 202021.25, 9 float64 (intrinsics K, row-major), 12 float64 (3x4 world-to-camera
  extrinsic E, row-major), so that a world point X projects as x = K E X.
- ``.flo`` (Middlebury): float32 tag 202021.25 (the bytes "PIEH"), int32 width, int32 height, then
  width*height*2 float32, u and v interleaved per pixel, row-major.

Readers return numpy arrays and raise :class:`~weathergen.errors.FormatError` naming the file for a
wrong tag, a truncated or oversized file, or implausible dimensions. Writers are atomic.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FormatError
from .atomic import atomic_write_bytes

TAG = np.float32(202021.25)
_MAX_SIDE = 1 << 16


def _read(path: str | Path) -> bytes:
    path = Path(path)
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except IsADirectoryError:
        raise FormatError(path, "is a folder, not a file") from None
    except OSError as exc:
        raise FormatError(path, f"cannot be read ({exc.strerror})") from None


def _check_tag(path: Path, data: bytes, kind: str) -> None:
    if len(data) < 4:
        raise FormatError(path, f"truncated: {len(data)} bytes, too short for a {kind} header")
    tag = np.frombuffer(data, "<f4", 1)[0]
    if tag != TAG:
        raise FormatError(path, f"bad header tag {float(tag)!r} (expected 202021.25): not a {kind} file")


def _read_grid(path: str | Path, channels: int, kind: str) -> np.ndarray:
    path = Path(path)
    data = _read(path)
    _check_tag(path, data, kind)
    if len(data) < 12:
        raise FormatError(path, f"truncated: {len(data)} bytes, too short for a {kind} header")
    w, h = (int(v) for v in np.frombuffer(data, "<i4", 2, offset=4))
    if not (0 < w < _MAX_SIDE and 0 < h < _MAX_SIDE):
        raise FormatError(path, f"implausible size {w}x{h} in header")
    expected = 12 + 4 * w * h * channels
    if len(data) != expected:
        state = "truncated" if len(data) < expected else "has trailing bytes"
        raise FormatError(path, f"{state}: {len(data)} bytes, expected {expected} for {w}x{h}")
    arr = np.frombuffer(data, "<f4", w * h * channels, offset=12).reshape(h, w, channels)
    return arr.astype(np.float32)


def _grid_bytes(arr: np.ndarray) -> bytes:
    h, w = arr.shape[:2]
    header = TAG.tobytes() + np.array([w, h], "<i4").tobytes()
    return header + np.ascontiguousarray(arr, "<f4").tobytes()


def read_dpt(path: str | Path) -> np.ndarray:
    """Read a ``.dpt`` depth map. Shape: returns (H, W) float32."""
    return _read_grid(path, 1, ".dpt depth")[..., 0]


def write_dpt(path: str | Path, depth: np.ndarray) -> Path:
    """Write a ``.dpt`` depth map atomically. Shape: depth (H, W)."""
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    return atomic_write_bytes(path, _grid_bytes(depth[..., None]))


def read_flo(path: str | Path) -> np.ndarray:
    """Read a Middlebury ``.flo`` flow field. Shape: returns (H, W, 2) float32, u then v."""
    return _read_grid(path, 2, ".flo flow")


def write_flo(path: str | Path, flow: np.ndarray) -> Path:
    """Write a ``.flo`` flow field atomically. Shape: flow (H, W, 2), u then v."""
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got shape {flow.shape}")
    return atomic_write_bytes(path, _grid_bytes(flow))


_CAM_BYTES = 4 + 8 * (9 + 12)


def read_cam(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a ``.cam`` file. Returns ``(K (3, 3), E (3, 4))`` float64, E world-to-camera."""
    path = Path(path)
    data = _read(path)
    _check_tag(path, data, ".cam camera")
    if len(data) != _CAM_BYTES:
        state = "truncated" if len(data) < _CAM_BYTES else "has trailing bytes"
        raise FormatError(path, f"{state}: {len(data)} bytes, expected {_CAM_BYTES}")
    vals = np.frombuffer(data, "<f8", 21, offset=4)
    if not np.isfinite(vals).all():
        raise FormatError(path, "camera matrices hold non-finite values")
    k = vals[:9].reshape(3, 3).copy()
    e = vals[9:].reshape(3, 4).copy()
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise FormatError(path, f"focal lengths must be positive, got fx={k[0, 0]}, fy={k[1, 1]}")
    return k, e


def write_cam(path: str | Path, intrinsics: np.ndarray, extrinsic: np.ndarray) -> Path:
    """Write a ``.cam`` file atomically. Shape: intrinsics (3, 3), extrinsic (3, 4) or (4, 4)."""
    k = np.asarray(intrinsics, np.float64)
    e = np.asarray(extrinsic, np.float64)[:3]
    if k.shape != (3, 3) or e.shape != (3, 4):
        raise ValueError(f"expected K (3, 3) and E (3, 4), got {k.shape} and {e.shape}")
    data = TAG.tobytes() + k.astype("<f8").tobytes() + e.astype("<f8").tobytes()
    return atomic_write_bytes(path, data)
