"""8-bit PNG weather frames (the default ``--format png``): colour only, in the pass folder."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ...io.images import read_image, write_png
from .base import FrameFormat


def write(path: Path, rgb: np.ndarray, opacity: np.ndarray) -> Path:
    """The frame as an 8-bit RGB PNG (the opacity is not stored)."""
    return write_png(path, rgb)


def size(path: Path) -> tuple[int, int]:
    """(height, width) of the frame."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        return read_image(path).shape[:2]    # names the file in its error
    return img.shape[:2]


FORMAT = FrameFormat(name="png", extension="png", folder_suffix="", write=write, read=read_image,
                     size=size)
