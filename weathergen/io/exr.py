"""OpenEXR float frames with extra channels (e.g. the particle opacity), written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

from ..errors import FormatError
from .atomic import atomic_path


def write_exr(path: str | Path, rgb: np.ndarray, extra: dict[str, np.ndarray] | None = None) -> Path:
    """Write a float32 RGB frame, plus named single-channel planes, as one ZIP-compressed EXR.

    Shape: rgb (H, W, 3) float; each extra plane (H, W).
    """
    path = Path(path)
    rgb = np.asarray(rgb, np.float32)
    channels = {"R": rgb[..., 0].copy(), "G": rgb[..., 1].copy(), "B": rgb[..., 2].copy()}
    for name, plane in (extra or {}).items():
        channels[name] = np.ascontiguousarray(plane, np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, suffix=".tmp.exr") as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))
    return path


def read_exr(path: str | Path) -> dict[str, np.ndarray]:
    """Read every channel of an EXR file: ``{"RGB": (H, W, 3), name: (H, W), ...}`` float32."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "file not found")
    try:
        with OpenEXR.File(str(path)) as f:
            return {name: np.asarray(ch.pixels, np.float32) for name, ch in f.channels().items()}
    except Exception as exc:  # the binding raises plain exceptions for corrupt files
        raise FormatError(path, f"cannot be read as OpenEXR ({exc})") from None
