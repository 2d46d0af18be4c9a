"""Synthetic frame pairs for the engine tests: planes at known depth seen by simple cameras."""

from __future__ import annotations

import math

import torch

from weathergen.framepair import FramePair, PairId


def rotation(roll_deg: float = 0.0, pitch_deg: float = 0.0, yaw_deg: float = 0.0) -> torch.Tensor:
    """Camera-from-world rotation for a camera rolled about z, pitched about x, yawed about y."""
    r, p, y = (math.radians(a) for a in (roll_deg, pitch_deg, yaw_deg))
    rz = torch.tensor([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1]])
    rx = torch.tensor([[1, 0, 0], [0, math.cos(p), -math.sin(p)], [0, math.sin(p), math.cos(p)]])
    ry = torch.tensor([[math.cos(y), 0, math.sin(y)], [0, 1, 0], [-math.sin(y), 0, math.cos(y)]])
    return (rz @ rx @ ry).double()


def pose(rot: torch.Tensor, centre=(0.0, 0.0, 0.0)) -> torch.Tensor:
    """cam_from_world for a camera with rotation ``rot`` (cam_from_world) at world ``centre``."""
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3] = rot
    out[:3, 3] = -rot @ torch.tensor(centre, dtype=torch.float64)
    return out


def plane_pair(height: int = 48, width: int = 64, depth: float = 4.0, *, world: bool = True,
               cam1_from_world: torch.Tensor | None = None,
               cam2_from_world: torch.Tensor | None = None, near_block: bool = False,
               dtype=torch.float32, seed: int = 0) -> FramePair:
    """A textured fronto-parallel plane at ``depth`` (optionally a near block at depth 1 in the
    left third); identity cameras unless given."""
    g = torch.Generator().manual_seed(seed)
    img1 = (0.2 + 0.6 * torch.rand(3, height, width, generator=g)).to(dtype)
    img2 = (0.2 + 0.6 * torch.rand(3, height, width, generator=g)).to(dtype)
    d = torch.full((1, height, width), depth, dtype=dtype)
    if near_block:
        d[..., : width // 3] = 1.0
    f = 0.8 * width
    k = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]],
                     dtype=torch.float64)
    c1 = cam1_from_world if cam1_from_world is not None else torch.eye(4, dtype=torch.float64)
    c2 = cam2_from_world if cam2_from_world is not None else torch.eye(4, dtype=torch.float64)
    rel = c2 @ torch.linalg.inv(c1)
    return FramePair(id=PairId("synthetic", "test", "plane", 1), image1=img1, image2=img2,
                     depth1=d, depth2=d.clone(), intrinsics=k, cam2_from_cam1=rel,
                     cam1_from_world=c1 if world else None, cam2_from_world=c2 if world else None)
