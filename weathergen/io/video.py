"""Video files: MP4 through OpenCV's writer, animated GIF through our own encoder (:mod:`.gif`).

OpenCV's FFmpeg back end writes MPEG-4 Part 2 video (``mp4v``) in an MP4 container without any
library beyond the OpenCV wheel; the H.264 encoders it knows are absent or need hardware. MPEG-4
Part 2 works on whole 2x2 blocks of colour samples, so frames of odd width or height are padded by
a copy of their last column or row (the writer would otherwise crop them). It is lossy (about 36 dB
PSNR on the demo scene; OpenCV offers no quality setting for it): GIF keeps up to 256 colours per
frame exactly. Both writers are atomic: the file appears under its name only once every frame is
written. OpenCV's writer does not report a failed write (a full disk leaves a truncated file
without its index), so an MP4 is checked before it gets its name (:func:`check_mp4`: the
container's boxes fill the file exactly, its index is there and counts every frame); a killed
writer's temporary file is removed by the next write of the same video
(:func:`~weathergen.io.atomic.remove_temporaries`).
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Iterable

import cv2
import numpy as np

from ..errors import ConfigError, OutputError
from .atomic import atomic_path, remove_temporaries
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

    remove_temporaries(path)        # those of an earlier writer that was killed
    if path.suffix.lower() == ".gif":
        write_gif(path, counted(), fps)
        return count
    with atomic_path(path, suffix=path.suffix) as tmp:   # the container follows the file name
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
        check_mp4(tmp, count, path)
    return count


def check_mp4(file: str | Path, frames: int, name: str | Path | None = None) -> None:
    """Check that ``file`` is a complete MP4 of ``frames`` frames: its top-level boxes fill it
    exactly, it has ``ftyp``, ``moov`` (the index) and ``mdat``, and the index's sample table
    (``stsz``) counts ``frames`` samples. Raises OSError naming ``name`` (default ``file``):
    ENOSPC when the disk holding it is full, else EIO."""
    file = Path(file)
    name = Path(name) if name is not None else file
    data = file.read_bytes()
    boxes = dict(_boxes(data, 0, len(data)))
    problem = None
    if boxes.get("_end") != len(data):
        problem = f"its boxes end at byte {boxes.get('_end')} of {len(data)} (truncated)"
    elif not {"ftyp", "moov", "mdat"} <= set(boxes):
        missing = sorted({"ftyp", "moov", "mdat"} - set(boxes))
        problem = f"no {', '.join(missing)} box ({len(data)} bytes written)"
    else:
        counts = _sample_counts(data, boxes["moov"])
        if frames not in counts:
            problem = f"its index counts {counts or 'no'} frames, not {frames}"
    if problem is None:
        return
    error = errno.ENOSPC if _disk_full(file.parent) else errno.EIO
    raise OSError(error, f"{os.strerror(error)}: the video is incomplete, {problem}", str(name))


def _boxes(data: bytes, start: int, end: int):
    """``(type, (payload start, box end))`` of the ISO-BMFF boxes in ``data[start:end]``, then
    ``("_end", where parsing stopped)`` (``end`` when the boxes fill the range exactly)."""
    at = start
    while at + 8 <= end:
        size = int.from_bytes(data[at:at + 4], "big")
        kind = data[at + 4:at + 8].decode("latin-1")
        head = 8
        if size == 1 and at + 16 <= end:
            size, head = int.from_bytes(data[at + 8:at + 16], "big"), 16
        elif size == 0:
            size = end - at
        if size < head or at + size > end:
            break
        yield kind, (at + head, at + size)
        at += size
    yield "_end", at


def _sample_counts(data: bytes, moov: tuple[int, int]) -> list[int]:
    """The sample count of each track's ``stsz`` box below ``moov``."""
    counts = []
    for kind, box in _boxes(data, *moov):
        if kind != "trak":
            continue
        for path in ("mdia", "minf", "stbl", "stsz"):
            box = dict(_boxes(data, *box)).get(path)
            if box is None:
                break
        if box is not None and box[1] - box[0] >= 12:
            counts.append(int.from_bytes(data[box[0] + 8:box[0] + 12], "big"))
    return counts


def _disk_full(folder: Path) -> bool:
    """Whether the file system holding ``folder`` has (almost) no room left."""
    try:
        st = os.statvfs(folder)
    except (OSError, AttributeError):
        return False
    return st.f_bavail * st.f_frsize < 1 << 20
