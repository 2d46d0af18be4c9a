"""Camera geometry: projection, back-projection, rigid transforms and reprojection flow.

Conventions are those of :mod:`weathergen.framepair`: OpenCV camera axes, pixel centres at integer
coordinates, ``(4, 4)`` transforms named ``a_from_b``. Every function works on leading batch
dimensions and keeps the dtype and device of its inputs, so it is differentiable.
"""

from __future__ import annotations

from typing import Optional

import torch

from .errors import ConfigError

#: The world-up settings that name an axis; besides these, "auto" and a direction "X,Y,Z".
WORLD_UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")


def project(points: torch.Tensor, intrinsics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Project camera-space points to pixels.

    Shape:
        points: (..., N, 3) camera coordinates; intrinsics: (..., 3, 3).
        returns ``(pixels (..., N, 2), depth (..., N))`` where depth is the camera z.
    Points with ``z <= 0`` produce meaningless pixels; callers must mask them by depth.
    """
    k = intrinsics.to(points.dtype)
    z = points[..., 2]
    safe_z = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
    fx, fy = k[..., 0, 0, None], k[..., 1, 1, None]
    cx, cy = k[..., 0, 2, None], k[..., 1, 2, None]
    skew = k[..., 0, 1, None]
    x = points[..., 0] / safe_z
    y = points[..., 1] / safe_z
    u = fx * x + skew * y + cx
    v = fy * y + cy
    return torch.stack((u, v), dim=-1), z


def pixel_grid(height: int, width: int, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """Pixel-centre coordinates.

    Shape: returns (2, H, W): channel 0 is x (column), channel 1 is y (row).
    """
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device),
        torch.arange(width, dtype=dtype, device=device),
        indexing="ij",
    )
    return torch.stack((xs, ys))


def backproject(depth: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Camera-space 3D point of every pixel, from camera-z depth.

    Shape: depth (..., 1, H, W), intrinsics (..., 3, 3) -> points (..., 3, H, W).
    """
    h, w = depth.shape[-2:]
    grid = pixel_grid(h, w, dtype=depth.dtype, device=depth.device)
    k = intrinsics.to(depth.dtype)
    fx, fy = k[..., 0, 0, None, None], k[..., 1, 1, None, None]
    cx, cy = k[..., 0, 2, None, None], k[..., 1, 2, None, None]
    skew = k[..., 0, 1, None, None]
    z = depth[..., 0, :, :]
    y = (grid[1] - cy) / fy
    x = (grid[0] - cx - skew * y) / fx
    return torch.stack((x * z, y * z, z), dim=-3)


def transform_points(a_from_b: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply a rigid (or any affine) ``(4, 4)`` transform to points.

    Shape: a_from_b (..., 4, 4), points (..., N, 3) -> (..., N, 3).
    """
    t = a_from_b.to(points.dtype)
    return points @ t[..., :3, :3].transpose(-1, -2) + t[..., None, :3, 3]


def invert_rigid(a_from_b: torch.Tensor) -> torch.Tensor:
    """Exact inverse of a rigid transform (rotation transposed, translation rotated back).

    Shape: (..., 4, 4) -> (..., 4, 4).
    """
    r = a_from_b[..., :3, :3]
    t = a_from_b[..., :3, 3:]
    out = torch.zeros_like(a_from_b)
    out[..., :3, :3] = r.transpose(-1, -2)
    out[..., :3, 3:] = -r.transpose(-1, -2) @ t
    out[..., 3, 3] = 1
    return out


def to_homogeneous(extrinsic_3x4: torch.Tensor) -> torch.Tensor:
    """Append the ``[0, 0, 0, 1]`` row to a ``(..., 3, 4)`` matrix."""
    bottom = torch.zeros(*extrinsic_3x4.shape[:-2], 1, 4, dtype=extrinsic_3x4.dtype,
                         device=extrinsic_3x4.device)
    bottom[..., 0, 3] = 1
    return torch.cat((extrinsic_3x4, bottom), dim=-2)


def reprojection_flow(depth1: torch.Tensor, intrinsics: torch.Tensor,
                      cam2_from_cam1: torch.Tensor) -> torch.Tensor:
    """Flow of a static scene: where each frame-1 pixel lands in frame 2.

    Shape: depth1 (..., 1, H, W), intrinsics (..., 3, 3), cam2_from_cam1 (..., 4, 4)
    -> flow (..., 2, H, W) in pixels.
    """
    h, w = depth1.shape[-2:]
    pts = backproject(depth1, intrinsics)                      # (..., 3, H, W)
    flat = pts.flatten(-2).transpose(-1, -2)                   # (..., HW, 3)
    pix2, _ = project(transform_points(cam2_from_cam1, flat), intrinsics)
    grid = pixel_grid(h, w, dtype=depth1.dtype, device=depth1.device)
    return pix2.transpose(-1, -2).reshape(*depth1.shape[:-3], 2, h, w) - grid


def rotation_angle_deg(rotation: torch.Tensor) -> torch.Tensor:
    """Angle of a rotation matrix in degrees. Shape: (..., 3, 3) -> (...)."""
    cos = ((rotation.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.rad2deg(torch.arccos(cos))


def up_direction(world_up: str) -> Optional[torch.Tensor]:
    """The world's up direction a world-up setting names: ``None`` for ``"auto"``, else a unit
    (3,) float64 vector. Settings: ``"auto"``, an axis ``"+x"`` … ``"-z"``, or a direction
    ``"X,Y,Z"`` in world coordinates, any length (for a world that is not level, e.g. a SLAM
    map in the first camera's axes, whose up is the measured gravity reversed).
    Raises :class:`~weathergen.errors.ConfigError` for anything else.
    """
    text = str(world_up).strip()
    if text == "auto":
        return None
    if text in WORLD_UP_AXES:
        out = torch.zeros(3, dtype=torch.float64)
        out["xyz".index(text[1])] = 1.0 if text[0] == "+" else -1.0
        return out
    parts = text.split(",")
    try:
        vec = torch.tensor([float(v) for v in parts], dtype=torch.float64) if len(parts) == 3 else None
    except ValueError:
        vec = None
    if vec is None or not bool(torch.isfinite(vec).all()) or float(vec.norm()) < 1e-9:
        raise ConfigError(f"world up {world_up!r}: must be auto, an axis ({', '.join(WORLD_UP_AXES)}) "
                          f"or a direction X,Y,Z of three numbers, not all zero (e.g. 0,-1,0)")
    return vec / vec.norm()
