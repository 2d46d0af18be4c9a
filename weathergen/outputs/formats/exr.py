"""Float OpenEXR weather frames (``--format exr``): colour and the particles' opacity as a channel
named ``opacity``, in the pass folder suffixed ``_exr``."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...io.exr import read_exr, write_exr
from .base import FrameFormat


def write(path: Path, rgb: np.ndarray, opacity: np.ndarray) -> Path:
    """The frame as float32 RGB with the opacity beside it."""
    return write_exr(path, rgb, {"opacity": opacity})


def read(path: Path) -> np.ndarray:
    """The colour, clipped to [0, 1] (an additive weather frame may exceed 1)."""
    return np.clip(read_exr(path)["RGB"], 0, 1)


def read_opacity(path: Path) -> np.ndarray:
    return read_exr(path)["opacity"]


def size(path: Path) -> tuple[int, int]:
    return read_exr(path)["RGB"].shape[:2]


FORMAT = FrameFormat(name="exr", extension="exr", folder_suffix="_exr", write=write, read=read,
                     size=size, read_opacity=read_opacity)
