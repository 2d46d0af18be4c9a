"""Files of the ``custom`` dataset layout: depth maps (.npy, 16-bit PNG, EXR) and camera files.

The layout and every key are specified in ``docs/datasets.md`` ("Your own data") and in
:mod:`weathergen.datasets.custom`. Readers raise :class:`~weathergen.errors.FormatError` naming the
file; writers are atomic.
"""

from __future__ import annotations

import io
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import OpenEXR

from ..errors import FormatError
from .text import read_text_file
from .atomic import atomic_write_bytes
from .images import read_raw

DEPTH_SUFFIXES = (".npy", ".png", ".exr")
#: The 16-bit PNG depth value read as missing besides 0 (sensors write it where they measured nothing).
PNG_DEPTH_MISSING = 65535
POSES = ("cam_from_world", "world_from_cam")
AXES = ("opencv", "opengl")
DEPTH_KINDS = ("z", "range")
#: EXR channel names tried, in order, for a depth map
_EXR_CHANNELS = ("Z", "depth", "Y", "R")


# -- depth ---------------------------------------------------------------------------------------
def read_depth(path: str | Path, png_scale: Optional[float] = None) -> np.ndarray:
    """Read a depth map by suffix. Shape: returns (H, W) float32 (0, NaN or inf where missing).

    ``.npy``: a float (H, W) or (H, W, 1) array. ``.png``: one-channel 16-bit, depth = value *
    ``png_scale`` (required); 0 and 65535 are missing (0 and NaN). ``.exr``: channel Z, depth, Y
    or R (or the only channel).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if not path.is_file():
        raise FormatError(path, "depth file not found" if not path.exists() else "is not a file")
    if suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise FormatError(path, f"is not a numpy .npy array ({exc})") from None
        if arr.ndim == 3 and arr.shape[2] == 1:
            arr = arr[..., 0]
        if arr.ndim != 2 or arr.dtype.kind not in "fiu":
            raise FormatError(path, f"holds a {arr.dtype} array of shape {arr.shape}, expected numbers (H, W)")
        return arr.astype(np.float32)
    if suffix == ".png":
        raw = read_raw(path)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise FormatError(path, f"depth PNG must be one-channel 16-bit, got {raw.dtype} with "
                                    f"{1 if raw.ndim == 2 else raw.shape[2]} channels")
        if png_scale is None:
            raise FormatError(path, "16-bit PNG depth needs 'depth_png_scale' (scene units per step) "
                                    "in the camera file")
        depth = raw.astype(np.float32) * np.float32(png_scale)
        # 0 and the saturated 65535 mean "no measurement" (Kinect-style sensors, 7-Scenes)
        depth[raw == PNG_DEPTH_MISSING] = np.nan
        return depth
    if suffix == ".exr":
        return _read_exr_depth(path)
    raise FormatError(path, f"unsupported depth format {suffix!r}; use .npy, 16-bit .png or .exr")


def _read_exr_depth(path: Path) -> np.ndarray:
    try:
        with OpenEXR.File(str(path)) as f:
            channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as exc:    # OpenEXR raises bare RuntimeErrors for every kind of failure
        raise FormatError(path, f"cannot be read as OpenEXR ({str(exc).splitlines()[0]})") from None
    for name in _EXR_CHANNELS:
        if name in channels and channels[name].ndim == 2:
            return channels[name].astype(np.float32)
    single = [a for a in channels.values() if a.ndim == 2]
    if len(channels) == 1 and single:
        return single[0].astype(np.float32)
    raise FormatError(path, f"has no depth channel (looked for {', '.join(_EXR_CHANNELS)}; found "
                            f"{', '.join(sorted(channels)) or 'none'})")


def write_depth(path: str | Path, depth: np.ndarray, png_scale: Optional[float] = None) -> Path:
    """Write a depth map by suffix (.npy, .png with ``png_scale``, .exr channel Z) atomically.

    Shape: depth (H, W); NaN/inf/<=0 are written as 0 in PNGs (missing); PNG values are clipped
    to 1 .. 65534 (65535 reads as missing).
    """
    path = Path(path)
    depth = np.asarray(depth, np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        buf = io.BytesIO()
        np.save(buf, depth)
        return atomic_write_bytes(path, buf.getvalue())
    if suffix == ".png":
        if not png_scale or png_scale <= 0:
            raise ValueError("a PNG depth map needs a positive png_scale")
        ok = np.isfinite(depth) & (depth > 0)
        coded = np.where(ok, np.clip(np.round(np.where(ok, depth, 0) / png_scale), 1,
                                     PNG_DEPTH_MISSING - 1), 0)
        done, buf = cv2.imencode(".png", coded.astype(np.uint16))
        if not done:
            raise RuntimeError("PNG encoding failed")
        return atomic_write_bytes(path, buf.tobytes())
    if suffix == ".exr":
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".exr", dir=path.parent)
        os.close(fd)
        try:
            header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
            with OpenEXR.File(header, {"Z": np.ascontiguousarray(depth)}) as f:
                f.write(tmp)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        return path
    raise ValueError(f"unsupported depth suffix {suffix!r}")


# -- cameras -------------------------------------------------------------------------------------
@dataclass
class CameraFile:
    """The content of a ``cameras.json`` / ``cameras.txt`` file, as written (not yet converted).

    ``intrinsics``: (3, 3) default for every frame; ``frames``: frame number (or, in JSON, a frame
    file's stem) -> ``(pose (4, 4), intrinsics (3, 3) or None)``; ``pose``, ``axes``, ``depth``:
    conventions (see the layout spec);
    ``depth_png_scale``: scene units per step of a 16-bit PNG depth map.
    """

    frames: dict = field(default_factory=dict)
    intrinsics: Optional[np.ndarray] = None
    pose: str = "cam_from_world"
    axes: str = "opencv"
    depth: str = "z"
    depth_png_scale: Optional[float] = None


def _intrinsics(path: Path, value, where: str) -> np.ndarray:
    if isinstance(value, dict):
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in value]
        if missing:
            raise FormatError(path, f"{where}: intrinsics lack {', '.join(missing)}")
        value = [[value["fx"], value.get("skew", 0.0), value["cx"]], [0, value["fy"], value["cy"]], [0, 0, 1]]
    try:
        k = np.array(value, np.float64)
    except (TypeError, ValueError):
        raise FormatError(path, f"{where}: intrinsics are not numbers") from None
    if k.shape != (3, 3) or not np.isfinite(k).all() or k[0, 0] <= 0 or k[1, 1] <= 0:
        raise FormatError(path, f"{where}: intrinsics must be a 3x3 matrix (or fx, fy, cx, cy) "
                                f"with positive focal lengths")
    return k


def _pose(path: Path, value, where: str) -> np.ndarray:
    try:
        m = np.array(value, np.float64)
    except (TypeError, ValueError):
        raise FormatError(path, f"{where}: pose is not a matrix of numbers") from None
    if m.shape == (12,) or m.shape == (16,):
        m = m.reshape(-1, 4)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise FormatError(path, f"{where}: pose must be a 3x4 or 4x4 matrix, got shape {m.shape}")
    rot = m[:3, :3]
    if np.abs(rot @ rot.T - np.eye(3)).max() > 1e-3 or np.linalg.det(rot) < 0:
        raise FormatError(path, f"{where}: pose is not a rigid transform (rotation not orthonormal)")
    return m


def _setting(path: Path, key: str, value, allowed: tuple[str, ...]) -> str:
    if value not in allowed:
        raise FormatError(path, f"{key} must be one of {', '.join(allowed)}, got {value!r}")
    return value


def read_camera_file(path: str | Path) -> CameraFile:
    """Read ``cameras.json`` or ``cameras.txt`` (format by suffix)."""
    path = Path(path)
    text = read_text_file(path, "camera")
    return _parse_json(path, text) if path.suffix.lower() == ".json" else _parse_txt(path, text)


_JSON_KEYS = {"intrinsics", "pose", "axes", "depth", "depth_png_scale", "frames"}


def _parse_json(path: Path, text: str) -> CameraFile:
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise FormatError(path, f"is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise FormatError(path, "must hold a JSON object")
    unknown = sorted(set(data) - _JSON_KEYS)
    if unknown:
        raise FormatError(path, f"unknown key {unknown[0]!r}; known: {', '.join(sorted(_JSON_KEYS))}")
    cams = CameraFile(
        pose=_setting(path, "pose", data.get("pose", "cam_from_world"), POSES),
        axes=_setting(path, "axes", data.get("axes", "opencv"), AXES),
        depth=_setting(path, "depth", data.get("depth", "z"), DEPTH_KINDS),
    )
    if "intrinsics" in data:
        cams.intrinsics = _intrinsics(path, data["intrinsics"], "intrinsics")
    if "depth_png_scale" in data:
        cams.depth_png_scale = _positive(path, "depth_png_scale", data["depth_png_scale"])
    frames = data.get("frames")
    if not isinstance(frames, dict) or not frames:
        raise FormatError(path, "needs a non-empty 'frames' object: frame number -> pose")
    for key, entry in frames.items():
        try:
            number = int(key)
        except ValueError:
            number = str(key)          # a frame file's stem, e.g. "000012_left"
        where = f"frame {key}"
        if isinstance(entry, dict):
            if "pose" not in entry:
                raise FormatError(path, f"{where}: needs a 'pose'")
            k = _intrinsics(path, entry["intrinsics"], where) if "intrinsics" in entry else None
            cams.frames[number] = (_pose(path, entry["pose"], where), k)
        else:
            cams.frames[number] = (_pose(path, entry, where), None)
    return cams


def _positive(path: Path, key: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        raise FormatError(path, f"{key} must be a positive number, got {value!r}")
    return float(value)


def _short(token: str, at_most: int = 40) -> str:
    """A token of a text file for a message, quoted and shortened."""
    return repr(token if len(token) <= at_most else token[: at_most - 3] + "...")


def _parse_txt(path: Path, text: str) -> CameraFile:
    cams = CameraFile()
    for i, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        if "=" in line:
            key, _, value = (s.strip() for s in line.partition("="))
            if key == "pose":
                cams.pose = _setting(path, key, value, POSES)
            elif key == "axes":
                cams.axes = _setting(path, key, value, AXES)
            elif key == "depth":
                cams.depth = _setting(path, key, value, DEPTH_KINDS)
            elif key == "depth_png_scale":
                try:
                    cams.depth_png_scale = _positive(path, key, float(value))
                except ValueError:
                    raise FormatError(path, f"line {i}: depth_png_scale must be a number") from None
            else:
                raise FormatError(path, f"line {i}: unknown setting {key!r}; known: pose, axes, "
                                        f"depth, depth_png_scale")
            continue
        parts = line.split()
        if len(parts) != 17:
            raise FormatError(path, f"line {i} has {len(parts)} values, expected 17: "
                                    f"frame fx fy cx cy and a 3x4 pose, row-major")
        try:
            number = int(parts[0])
        except ValueError:
            raise FormatError(path, f"line {i} is not a frame number followed by 16 numbers: "
                                    f"{_short(parts[0])} is not a whole frame number") from None
        vals = []
        for v in parts[1:]:
            try:
                vals.append(float(v))
            except ValueError:
                raise FormatError(path, f"line {i} is not a frame number followed by 16 numbers: "
                                        f"{_short(v)} is not a number") from None
        fx, fy, cx, cy = vals[:4]
        k = _intrinsics(path, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], f"line {i}")
        cams.frames[number] = (_pose(path, vals[4:], f"line {i}"), k)
    if not cams.frames:
        raise FormatError(path, "holds no camera lines (frame fx fy cx cy r11 r12 r13 t1 ... t3)")
    return cams


def write_camera_json(path: str | Path, frames: dict, intrinsics: Optional[np.ndarray] = None, *,
                      pose: str = "cam_from_world", axes: str = "opencv", depth: str = "z",
                      depth_png_scale: Optional[float] = None) -> Path:
    """Write ``cameras.json`` atomically. ``frames``: frame number -> (4, 4) pose, or (pose, K)."""
    out: dict = {"pose": pose, "axes": axes, "depth": depth}
    if intrinsics is not None:
        out["intrinsics"] = np.asarray(intrinsics, float).tolist()
    if depth_png_scale is not None:
        out["depth_png_scale"] = depth_png_scale
    entries = {}
    for number, value in sorted(frames.items()):
        if isinstance(value, tuple):
            p, k = value
            entries[str(number)] = {"pose": np.asarray(p, float).tolist(),
                                    **({"intrinsics": np.asarray(k, float).tolist()} if k is not None else {})}
        else:
            entries[str(number)] = np.asarray(value, float).tolist()
    out["frames"] = entries
    return atomic_write_bytes(path, (json.dumps(out, indent=1) + "\n").encode())


def write_camera_txt(path: str | Path, frames: dict, intrinsics: np.ndarray, **settings) -> Path:
    """Write ``cameras.txt`` atomically: settings lines, then ``frame fx fy cx cy`` + 3x4 pose per line."""
    k = np.asarray(intrinsics, float)
    lines = ["# frame fx fy cx cy r11 r12 r13 t1 r21 r22 r23 t2 r31 r32 r33 t3"]
    lines += [f"{key} = {value}" for key, value in settings.items()]
    for number, p in sorted(frames.items()):
        vals = [k[0, 0], k[1, 1], k[0, 2], k[1, 2], *np.asarray(p, float)[:3].ravel()]
        lines.append(f"{number} " + " ".join(f"{v:.12g}" for v in vals))
    return atomic_write_bytes(path, ("\n".join(lines) + "\n").encode())
