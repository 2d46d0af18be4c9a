"""Readers and writers of the Spring formats: HDF5 disparity and flow, camera text files.

Formats (public facts of the Spring benchmark's data release):
- ``.dsp5``: an HDF5 file with a dataset ``disparity``, float32 (2H, 2W) for frames of H x W:
  the ground truth is stored at twice the image resolution in each direction, every image pixel
  split into 2x2 samples. Values are in pixels *of the image* (not of the doubled grid); invalid
  samples are NaN (or not positive).
- ``.flo5``: an HDF5 file with a dataset ``flow``, float32 (2H, 2W, 2), u then v, likewise in image
  pixels; NaN marks samples without ground truth.
- ``cam_data/intrinsics.txt``: one line per frame (frame 1 first): ``fx fy cx cy`` in pixels.
- ``cam_data/extrinsics.txt``: one 4x4 matrix per frame, 16 numbers row-major on one line (four
  lines of four numbers are read too). How the reader interprets them: see
  :mod:`weathergen.datasets.spring`.

Readers return numpy arrays and raise :class:`~weathergen.errors.FormatError` naming the file.
Writers are atomic (written to a temporary file in the folder, then renamed).
"""

from __future__ import annotations

import io
from pathlib import Path

import h5py
import numpy as np

from ..errors import FormatError
from .text import read_text_file
from .atomic import atomic_write_bytes


# -- HDF5 ----------------------------------------------------------------------------------------
def _read_h5(path: Path, key: str, kind: str) -> np.ndarray:
    if not path.is_file():
        raise FormatError(path, "file not found" if not path.exists() else "is not a file")
    try:
        with h5py.File(path, "r") as f:
            if key not in f:
                found = ", ".join(sorted(f.keys())) or "none"
                raise FormatError(path, f"has no '{key}' dataset (found: {found}); not a {kind} file")
            node = f[key]
            if not isinstance(node, h5py.Dataset):
                raise FormatError(path, f"'{key}' is a group, not a dataset; not a {kind} file")
            return np.asarray(node[()], dtype=np.float32)
    except OSError as exc:
        raise FormatError(path, f"cannot be read as HDF5 ({kind}): {exc}") from None


def _write_h5(path: str | Path, key: str, data: np.ndarray) -> Path:
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.create_dataset(key, data=np.asarray(data, np.float32), compression="gzip", compression_opts=4)
    return atomic_write_bytes(path, buf.getvalue())


def read_dsp5(path: str | Path) -> np.ndarray:
    """Read a Spring disparity file. Shape: returns (h, w) float32 pixels, NaN/<=0 where invalid."""
    path = Path(path)
    disp = _read_h5(path, "disparity", ".dsp5 disparity")
    if disp.ndim != 2:
        raise FormatError(path, f"disparity has shape {disp.shape}, expected (height, width)")
    return disp


def write_dsp5(path: str | Path, disparity: np.ndarray) -> Path:
    """Write a Spring disparity file atomically. Shape: disparity (h, w), NaN where invalid."""
    disparity = np.asarray(disparity)
    if disparity.ndim != 2:
        raise ValueError(f"disparity must be (h, w), got shape {disparity.shape}")
    return _write_h5(path, "disparity", disparity)


def read_flo5(path: str | Path) -> np.ndarray:
    """Read a Spring flow file. Shape: returns (h, w, 2) float32 pixels, u then v, NaN where invalid."""
    path = Path(path)
    flow = _read_h5(path, "flow", ".flo5 flow")
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise FormatError(path, f"flow has shape {flow.shape}, expected (height, width, 2)")
    return flow


def write_flo5(path: str | Path, flow: np.ndarray) -> Path:
    """Write a Spring flow file atomically. Shape: flow (h, w, 2), NaN where invalid."""
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (h, w, 2), got shape {flow.shape}")
    return _write_h5(path, "flow", flow)


# -- resolution ----------------------------------------------------------------------------------
def reduce_2x2(samples: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Halve a (2H, 2W) ground-truth grid to the (H, W) image grid, one *measured* value per pixel.

    Shape: samples (2H, 2W) or (2H, 2W, C); valid (2H, 2W) bool -> ``(values (H, W[, C]) float32,
    valid (H, W) bool)``.

    Of the valid samples of each 2x2 block we keep the medoid: the one with the smallest summed
    distance to the others (ties: the first in raster order). Averaging would invent values at
    depth and motion edges, where a block straddles a foreground object and the background
    (a "flying" depth that belongs to no surface); the medoid is always a real sample and, with
    three or four samples, ignores a single outlier. Blocks without a valid sample are invalid.
    """
    squeeze = samples.ndim == 2
    s = samples[..., None] if squeeze else samples
    h2, w2, c = s.shape
    if h2 % 2 or w2 % 2 or valid.shape != (h2, w2):
        raise ValueError(f"expected an even-sized grid and a matching mask, got {s.shape} and {valid.shape}")
    h, w = h2 // 2, w2 // 2
    # (H, W, 4, C): the four samples of each block, raster order within the block
    blocks = s.reshape(h, 2, w, 2, c).transpose(0, 2, 1, 3, 4).reshape(h, w, 4, c).astype(np.float64)
    ok = valid.reshape(h, 2, w, 2).transpose(0, 2, 1, 3).reshape(h, w, 4)
    safe = np.where(ok[..., None], blocks, 0.0)
    dist = np.abs(safe[:, :, :, None, :] - safe[:, :, None, :, :]).sum(-1)    # (H, W, 4, 4)
    dist = np.where(ok[:, :, None, :], dist, 0.0).sum(-1)                      # to valid ones only
    dist = np.where(ok, dist, np.inf)
    pick = np.argmin(dist, axis=-1)
    out = np.take_along_axis(blocks, pick[..., None, None], axis=2)[:, :, 0, :].astype(np.float32)
    any_ok = ok.any(-1)
    out[~any_ok] = np.nan
    return (out[..., 0] if squeeze else out), any_ok


# -- cameras -------------------------------------------------------------------------------------
def _read_numbers(path: Path, kind: str) -> np.ndarray:
    text = read_text_file(path, kind)
    rows = []
    for i, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        try:
            rows.append([float(v) for v in line.split()])
        except ValueError:
            raise FormatError(path, f"line {i} is not a list of numbers: {line[:60]!r}") from None
    values = np.array([v for r in rows for v in r], np.float64)
    if not np.isfinite(values).all():
        raise FormatError(path, f"{kind} hold non-finite values")
    return values


def read_intrinsics_txt(path: str | Path) -> np.ndarray:
    """Read ``intrinsics.txt``. Shape: returns (N, 4) float64 rows ``fx fy cx cy``, frame 1 first."""
    path = Path(path)
    values = _read_numbers(path, "intrinsics")
    if values.size == 0 or values.size % 4:
        raise FormatError(path, f"holds {values.size} numbers, expected 4 per frame (fx fy cx cy)")
    rows = values.reshape(-1, 4)
    if (rows[:, :2] <= 0).any():
        raise FormatError(path, "focal lengths must be positive")
    return rows


def write_intrinsics_txt(path: str | Path, rows: np.ndarray) -> Path:
    """Write ``intrinsics.txt`` atomically. Shape: rows (N, 4) ``fx fy cx cy``."""
    rows = np.asarray(rows, np.float64).reshape(-1, 4)
    return atomic_write_bytes(path, "".join(" ".join(f"{v:.10g}" for v in r) + "\n" for r in rows).encode())


def read_extrinsics_txt(path: str | Path) -> np.ndarray:
    """Read ``extrinsics.txt``. Shape: returns (N, 4, 4) float64, frame 1 first (convention: see above)."""
    path = Path(path)
    values = _read_numbers(path, "extrinsics")
    if values.size == 0 or values.size % 16:
        raise FormatError(path, f"holds {values.size} numbers, expected 16 per frame (a 4x4 matrix)")
    mats = values.reshape(-1, 4, 4)
    rot = mats[:, :3, :3]
    err = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = np.nonzero((err > 1e-3) | (np.abs(mats[:, 3] - [0, 0, 0, 1]).max(1) > 1e-6))[0]
    if bad.size:
        raise FormatError(path, f"matrix {bad[0] + 1} is not a rigid transform (rotation not "
                                f"orthonormal or last row not 0 0 0 1)")
    return mats


def write_extrinsics_txt(path: str | Path, mats: np.ndarray) -> Path:
    """Write ``extrinsics.txt`` atomically, one 4x4 matrix per line. Shape: mats (N, 4, 4)."""
    mats = np.asarray(mats, np.float64).reshape(-1, 16)
    return atomic_write_bytes(path, "".join(" ".join(f"{v:.12g}" for v in m) + "\n" for m in mats).encode())
