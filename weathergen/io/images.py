"""8/16-bit PNG frames and masks, read and written with OpenCV, converted to our RGB conventions."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import FormatError
from .atomic import atomic_write_bytes

#: OpenCV's log level "errors only" (the value of cv2.utils.logging.LOG_LEVEL_ERROR).
_CV_LOG_LEVEL_ERROR = 2


def quiet_opencv() -> None:
    """Let OpenCV log errors only.

    Our own errors name the file and the problem; OpenCV's warnings about the same corrupt file
    ("buffer is incomplete") would only add a second, vaguer line. ``cv2.utils.logging`` is
    missing from some wheels (4.8 and 4.11 among them), where the older ``cv2.setLogLevel`` does
    the same; with neither, OpenCV keeps its default level.
    """
    logging = getattr(getattr(cv2, "utils", None), "logging", None)
    if logging is not None and hasattr(logging, "setLogLevel"):
        logging.setLogLevel(getattr(logging, "LOG_LEVEL_ERROR", _CV_LOG_LEVEL_ERROR))
    elif hasattr(cv2, "setLogLevel"):
        cv2.setLogLevel(_CV_LOG_LEVEL_ERROR)


quiet_opencv()


def read_image(path: str | Path) -> np.ndarray:
    """Read an RGB frame. Shape: returns (H, W, 3) float32 in [0, 1] (8- or 16-bit sources).

    Grey-scale files are replicated to three channels; an alpha channel is dropped.
    """
    return rgb_from_raw(read_raw(path), path)


def read_image_kind(path: str | Path) -> tuple[np.ndarray, str]:
    """:func:`read_image`, and what the file stores: ``"grey"`` or ``"colour"`` (alpha aside)."""
    raw = read_raw(path)
    return rgb_from_raw(raw, path), ("grey" if raw.ndim == 2 else "colour")


def rgb_from_raw(raw: np.ndarray, path: str | Path) -> np.ndarray:
    """An image as :func:`read_raw` returns it, as :func:`read_image` returns it; ``path`` names
    the file in errors."""
    path = Path(path)
    if raw.dtype == np.uint8:
        scale = 255.0
    elif raw.dtype == np.uint16:
        scale = 65535.0
    else:
        raise FormatError(path, f"unsupported pixel type {raw.dtype} (expected 8- or 16-bit)")
    if raw.ndim == 2:
        raw = np.repeat(raw[..., None], 3, axis=2)
    elif raw.shape[2] == 4:
        raw = raw[..., :3]
    elif raw.shape[2] != 3:
        raise FormatError(path, f"has {raw.shape[2]} channels, expected 1, 3 or 4")
    rgb = raw[..., ::-1]  # OpenCV stores BGR
    return np.ascontiguousarray(rgb, dtype=np.float32) / np.float32(scale)


def read_raw(path: str | Path) -> np.ndarray:
    """Read an image file as stored (BGR order, native bit depth), with clear errors."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "file not found" if not path.exists() else "is not a file")
    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise FormatError(path, "cannot be decoded as an image (corrupt or not an image)")
    return img


def encode_png(rgb: np.ndarray) -> bytes:
    """Encode an RGB image as 8-bit PNG bytes.

    Shape: rgb (H, W, 3) float in [0, 1] (rounded to nearest) or uint8; (H, W) for grey.
    """
    arr = to_uint8(rgb)
    if arr.ndim == 3:
        arr = arr[..., ::-1]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB (or grey) image as an 8-bit PNG, atomically."""
    return atomic_write_bytes(path, encode_png(rgb))


def write_png16(path: str | Path, grey: np.ndarray) -> Path:
    """Write a grey image in [0, 1] as a 16-bit PNG (value x 65535, rounded), atomically.

    Shape: grey (H, W) float.
    """
    arr = (np.clip(np.asarray(grey, dtype=np.float64), 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(arr))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return atomic_write_bytes(path, buf.tobytes())


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float [0, 1] -> uint8 with rounding and clipping; uint8 passes through."""
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
