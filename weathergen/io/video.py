"""Video files: MP4 through OpenCV's writer, animated GIF through our own encoder (:mod:`.gif`).

OpenCV's FFmpeg back end writes MPEG-4 Part 2 video (``mp4v``) in an MP4 container without any
library beyond the OpenCV wheel; the H.264 encoders it knows are absent or need hardware. MPEG-4
Part 2 works on whole 2x2 blocks of colour samples, so frames of odd width or height are padded by
a copy of their last column or row (the writer would otherwise crop them). It is lossy (about 36 dB
PSNR on the demo scene; OpenCV offers no quality setting for it): GIF keeps up to 256 colours per
frame exactly. Both writers are atomic: the file
appears under its name only once every frame is written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from ..errors import ConfigError, OutputError
from .atomic import atomic_path
from .gif import write_gif

#: File extensions a video can be written as.
VIDEO_SUFFIXES = (".mp4", ".gif")
#: OpenCV's code of the MP4 codec it can write everywhere (MPEG-4 Part 2).
MP4_FOURCC = "mp4v"


def check_video_path(path: str | Path) -> Path:
    """``path`` as a :class:`Path` when its extension is one of :data:`VIDEO_SUFFIXES`; else
    :class:`ConfigError` naming ``${video}``."""
    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise ConfigError(f"${{video}} {path}: unknown video format "
                          f"{path.suffix or '(no extension)'!r}; use {' or '.join(VIDEO_SUFFIXES)}")
    return path


def even_size(rgb: np.ndarray) -> np.ndarray:
    """The frame padded to an even width and height by repeating its last column or row.
    Shape: (H, W, 3) -> (H', W', 3)."""
    h, w = rgb.shape[:2]
    if h % 2 == 0 and w % 2 == 0:
        return rgb
    return np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Write ``frames`` as a video at ``fps`` frames per second; the extension of ``path`` picks
    the format (``.mp4`` or ``.gif``). Returns the number of frames written.

    Shape: frames (H, W, 3) uint8 RGB, all of one size. Raises ConfigError for another extension,
    OutputError when the video cannot be encoded, OSError when the file cannot be written (no file
    is left behind in any case, see :mod:`weathergen.io.atomic`).
    """
    path = check_video_path(path)
    if not fps > 0:
        raise ConfigError(f"${{fps}} {fps!r}: must be > 0")
    count = 0

    def counted():
        nonlocal count
        for rgb in frames:
            count += 1
            yield rgb

    if path.suffix.lower() == ".gif":
        write_gif(path, counted(), fps)
        return count
    with atomic_path(path, suffix=".mp4") as tmp:   # the container follows the file name
        writer = None
        try:
            for rgb in counted():
                rgb = even_size(np.asarray(rgb, np.uint8))
                if writer is None:
                    size = (rgb.shape[1], rgb.shape[0])
                    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*MP4_FOURCC),
                                             float(fps), size)
                    if not writer.isOpened():
                        raise OutputError(f"{path}: OpenCV cannot write {MP4_FOURCC} video here")
                elif (rgb.shape[1], rgb.shape[0]) != size:
                    raise ValueError(f"video frames must share one size: {size[0]}x{size[1]}, "
                                     f"then {rgb.shape[1]}x{rgb.shape[0]}")
                writer.write(np.ascontiguousarray(rgb[..., ::-1]))     # OpenCV takes BGR
        finally:
            if writer is not None:
                writer.release()
        if writer is None:
            raise ValueError("a video needs at least one frame")
    return count
