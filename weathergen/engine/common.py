"""What sampling and rendering both need of a frame pair: its check, the reference frame its
particles live in, the device it is drawn on and the nearest depth a particle may have."""

from __future__ import annotations

from typing import Optional, Union

import torch

from ..errors import DatasetError, WeatherGenError
from ..framepair import FramePair

NEAR = 1e-3  # nearest camera depth a particle may have, scene units


def resolve_device(device: Optional[Union[str, torch.device]]) -> torch.device:
    """``None`` -> CPU; raise a one-line WeatherGenError for a device this machine lacks."""
    if device is None:
        return torch.device("cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise WeatherGenError(f"unknown device {device!r} (use cpu, cuda or cuda:N)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise WeatherGenError(f"device {device!r} requested but CUDA is not available "
                                  "on this machine (use ${device} cpu)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise WeatherGenError(f"device {device!r} requested but only "
                                  f"{torch.cuda.device_count()} CUDA device(s) exist")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise WeatherGenError(f"device {device!r} requested but MPS is not available")
    return dev


def reference_transforms(pair: FramePair) -> tuple[str, torch.Tensor, torch.Tensor]:
    """The reference frame particles of ``pair`` live in, and both cameras' transforms from it.

    Returns ``(frame, cam1_from_ref, cam2_from_ref)``, frame ``"world"`` where the pair has
    absolute poses, else ``"camera1"``. Shape: (4, 4) float64 each.
    """
    if pair.cam1_from_world is not None and pair.cam2_from_world is not None:
        return "world", pair.cam1_from_world.double(), pair.cam2_from_world.double()
    eye = torch.eye(4, dtype=torch.float64, device=pair.cam2_from_cam1.device)
    return "camera1", eye, pair.cam2_from_cam1.double()


def check_pair_for_engine(pair: FramePair) -> None:
    """Raise DatasetError when ``pair`` lacks what the engine needs (depth, cameras)."""
    where = pair.sources.get("image1", pair.id)
    for name in ("depth1", "depth2"):
        if getattr(pair, name, None) is None:
            raise DatasetError(f"{where}: frame pair has no {name}; weather needs scene depth")
    if pair.intrinsics is None or pair.cam2_from_cam1 is None:
        raise DatasetError(f"{where}: frame pair has no camera intrinsics or relative pose")
    pair.validate()
