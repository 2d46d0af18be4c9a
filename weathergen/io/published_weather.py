"""The particle files of the paper's research code, as its authors published the paper's weather.

The research code behind "Distracting Downpour" (cv-stuttgart/DistractingDownpour) saves the
particles of one Sintel frame pair with ``numpy.savez`` (its ``save_weatherfile``), one file per
pair, laid out by scene and frame as its generator writes them and as the published ``_npz`` data
sets hold them::

    SET/SCENE/frame_0001.npz        the pair (frame 1, frame 2) of SCENE
    SET/SCENE/frame_1_0001.png      (the rendered frames, in the ``_png`` sets and the generator's
    SET/SCENE/frame_2_0001.png       own output; not read here)

Each file holds five float32 arrays, batch dimension first (always 1), N particles:

    points3D     (1, N, 4)        homogeneous positions in camera-1 coordinates (x right, y down,
                                  z forward; w = 1), in the units of the scene as the research
                                  code scaled it
    motion3D     (1, N, 4)        each particle's motion between the frames, in camera-2
                                  coordinates (w = 0): frame 2 holds R X + t + m
    flakes       (1, N, 4, S, S)  each particle's flake image, S odd: RGB colour offsets (zero in
                                  every published set: the templates' colour channels are empty)
                                  and the alpha its renderer draws, already scaled to the
                                  particle's depth and blurred (the rotation's cubic spline
                                  leaves values slightly below 0, down to about -0.01, which its
                                  renderer cuts off after placing the flake)
    flakescol    (1, N, 3)        each particle's RGB colour in [0, 1]
    flakestrans  (1, N)           each particle's transparency before its transform: drawn with
                                  θ = s · (tanh(value) + 1) / 2, s the render's transparency scale

:func:`read_published_weather` reads and checks one file; :func:`published_file` says where a
pair's file lies; :func:`is_published_set` whether a folder is such a set.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import FormatError

#: The arrays of a file, as ``save_weatherfile`` names them.
ARRAYS = ("points3D", "motion3D", "flakes", "flakescol", "flakestrans")


@dataclass
class PublishedWeather:
    """One pair's particles as the research code stores them (batch dimension dropped).

    Shape: points (N, 3) camera-1 coordinates; motion (N, 3) camera-2 axes; alpha (N, S, S) the
    flakes' alpha; color (N, 3) in [0, 1]; transparency (N,) before ``s (tanh + 1) / 2``; all
    float32 as stored. ``path``: the file.
    """

    points: np.ndarray
    motion: np.ndarray
    alpha: np.ndarray
    color: np.ndarray
    transparency: np.ndarray
    path: Path

    @property
    def count(self) -> int:
        return int(self.points.shape[0])

    @property
    def side(self) -> int:
        return int(self.alpha.shape[-1])


def published_file(folder: str | Path, scene: str, frame: int) -> Path:
    """Where a published set keeps the particles of the pair that starts at ``frame`` of
    ``scene`` (Sintel's frame numbers, from 1)."""
    return Path(folder) / scene / f"frame_{int(frame):04d}.npz"


def is_published_set(folder: str | Path) -> bool:
    """Whether ``folder`` is laid out as a published set (``SCENE/frame_NNNN.npz`` files, no
    manifest) rather than a weathergen output (which has a manifest and deeper folders); its
    files are checked when read (:func:`read_published_weather` names a bad one)."""
    folder = Path(folder)
    if not folder.is_dir() or (folder / "manifest.json").exists():
        return False
    return any(path.is_file() for path in folder.glob("*/frame_[0-9][0-9][0-9][0-9].npz"))


def is_published_file(path: str | Path) -> bool:
    """Whether ``path`` claims to be a file of the research code: an ``.npz`` archive holding
    any of its arrays (which :func:`read_published_weather` then checks)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return any(k in data.files for k in ARRAYS)
    except Exception:           # not a file, not an archive: not one of these
        return False


def _load(path: Path) -> dict:
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except FileNotFoundError:
        raise FormatError(path, "no such particle file") from None
    except OSError as exc:
        raise FormatError(path, f"cannot be read ({exc.strerror or exc})") from None
    if not head:
        raise FormatError(path, "an empty file (expected the .npz archive of the research "
                                "code's particle arrays)")
    if head[:2] != b"PK":
        raise FormatError(path, "not an .npz archive (the research code's particle files are "
                                "zips of numpy arrays)")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except Exception as exc:            # corrupt archives raise several types
        raise FormatError(path, f"not a readable .npz file, truncated or damaged "
                                f"({' '.join(str(exc).split())})") from None


def read_published_weather(path: str | Path) -> PublishedWeather:
    """Read and check one file of the research code's format (see the module doc).

    Raises:
        FormatError: naming the file: an array missing, of the wrong shape or type, a batch of
            more than one pair, non-finite values, a homogeneous coordinate that is not 1 (0 for
            the motion), an even flake side, or flakes with colour in their RGB channels (which
            weathergen does not draw; no published set has any).
    """
    path = Path(path)
    arrays = _load(path)
    missing = [k for k in ARRAYS if k not in arrays]
    if missing:
        raise FormatError(path, f"not the research code's particle file: no {', '.join(missing)} "
                                f"(expected the arrays {', '.join(ARRAYS)})")
    points, motion, flakes, color, trans = (np.asarray(arrays[k]) for k in ARRAYS)
    if points.ndim != 3 or points.shape[0] != 1 or points.shape[2] != 4:
        raise FormatError(path, f"points3D must be (1, N, 4), got {points.shape}")
    n = points.shape[1]
    expected = {"motion3D": (1, n, 4), "flakescol": (1, n, 3), "flakestrans": (1, n)}
    for name, a in (("motion3D", motion), ("flakescol", color), ("flakestrans", trans)):
        if a.shape != expected[name]:
            raise FormatError(path, f"{name} must be {expected[name]} for {n} particles, got {a.shape}")
    if flakes.ndim != 5 or flakes.shape[:3] != (1, n, 4) or flakes.shape[3] != flakes.shape[4]:
        raise FormatError(path, f"flakes must be (1, {n}, 4, S, S), got {flakes.shape}")
    side = flakes.shape[-1]
    if side % 2 == 0:
        raise FormatError(path, f"flakes must have an odd side (the particle at their centre), "
                                f"got {side}")
    for name, a in zip(ARRAYS, (points, motion, flakes, color, trans)):
        if not np.issubdtype(a.dtype, np.floating):
            raise FormatError(path, f"{name} must hold floats, got {a.dtype}")
        if not np.isfinite(a).all():
            raise FormatError(path, f"{name} holds values that are not finite")
    if n and not np.allclose(points[0, :, 3], 1.0):
        raise FormatError(path, "points3D's fourth (homogeneous) coordinate must be 1")
    if n and not np.allclose(motion[0, :, 3], 0.0):
        raise FormatError(path, "motion3D's fourth (homogeneous) coordinate must be 0")
    if n and np.any(flakes[0, :, :3] != 0):
        raise FormatError(path, "flakes carry colour offsets in their RGB channels, which "
                                "weathergen does not draw (every published set has none: the "
                                "flake templates' colour channels are empty)")
    alpha = flakes[0, :, 3]
    return PublishedWeather(points=points[0, :, :3].astype(np.float32, copy=False),
                            motion=motion[0, :, :3].astype(np.float32, copy=False),
                            alpha=alpha.astype(np.float32, copy=False),
                            color=color[0].astype(np.float32, copy=False),
                            transparency=trans[0].astype(np.float32, copy=False), path=path)
