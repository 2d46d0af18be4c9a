"""The second camera of a stereo dataset: its frames and where it sits relative to the first.

Rendering weather into a stereo rig needs, per pair, the right camera's two frames and the
transform ``right_from_left`` (rectified rigs: a translation by the baseline along -x, as the
right camera sits at +x). Where the datasets keep them:

- KITTI 2015: ``SPLIT/image_3/NNNNNN_10.png`` and ``_11.png``; the baseline from
  ``calib_cam_to_cam`` (``P_rect_02`` and ``P_rect_03``), as the reader already reads it;
- Spring: ``SPLIT/SCENE/frame_right/frame_right_FFFF.png``; the reader's baseline (0.065 m);
- your own data (custom layout): ``SCENE/right/frames/`` with the same file names as
  ``SCENE/frames/``, and ``SCENE/right/camera.json`` holding ``{"right_from_left": 4x4 or 3x4
  matrix}`` (OpenCV axes, scene units before the depth scale; the right camera shares the left
  one's intrinsics unless the file gives ``"intrinsics"`` as a 3x3 matrix).

Baselines and translations are multiplied by the pair's depth scale, like every other length.
Each reader says whether it has a second camera (its class attribute ``stereo``) and reads it
(its method ``right_camera``); :func:`weathergen.datasets.right_camera` refuses the others with a
:class:`~weathergen.errors.ConfigError`.
"""

from __future__ import annotations

from dataclasses import dataclass
import json
from pathlib import Path
from typing import Optional

import torch

from ..errors import DatasetError
from ..framepair import FramePair
from ..io.images import read_image

@dataclass
class RightCamera:
    """Shape: image1, image2 (3, H, W) float32 in [0, 1]; right_from_left (4, 4) float64."""

    image1: torch.Tensor
    image2: torch.Tensor
    right_from_left: torch.Tensor
    baseline: float
    sources: tuple
    intrinsics: Optional[torch.Tensor] = None     # None: the left camera's


def rectified_right(files: tuple[Path, Path], baseline: float, pair: FramePair) -> RightCamera:
    """The right camera of a rectified rig: its two frame ``files`` and the ``baseline`` in scene
    units (before the pair's depth scale); the right camera sits at +x, sharing the intrinsics."""
    images = _read_right(files, pair)
    baseline *= pair.depth_scale
    right_from_left = torch.eye(4, dtype=torch.float64)
    right_from_left[0, 3] = -baseline
    return RightCamera(images[0], images[1], right_from_left, baseline, tuple(files))


def custom_right(pair: FramePair) -> RightCamera:
    """The right camera of the custom layout: ``SCENE/right/camera.json`` and ``SCENE/right/frames/``."""
    frame1 = Path(pair.sources["image1"])
    scene = frame1.parent.parent
    camera = scene / "right" / "camera.json"
    if not camera.is_file():
        raise DatasetError(f"{camera}: right camera file not found (needed for stereo; it holds "
                           '{"right_from_left": [[...4x4...]]})')
    try:
        data = json.loads(camera.read_text())
        matrix = torch.tensor(data["right_from_left"], dtype=torch.float64)
        intrinsics = (torch.tensor(data["intrinsics"], dtype=torch.float64)
                      if "intrinsics" in data else None)
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{camera}: not a right camera file ({exc}); expected "
                           '{"right_from_left": 4x4 matrix}') from None
    if matrix.shape == (3, 4):
        matrix = torch.cat((matrix, torch.tensor([[0, 0, 0, 1.0]], dtype=torch.float64)))
    if matrix.shape != (4, 4) or not bool(torch.isfinite(matrix).all()):
        raise DatasetError(f"{camera}: right_from_left must be a finite 4x4 or 3x4 matrix")
    if intrinsics is not None and intrinsics.shape != (3, 3):
        raise DatasetError(f"{camera}: intrinsics must be a 3x3 matrix")
    matrix[:3, 3] *= pair.depth_scale
    files = tuple(scene / "right" / "frames" / Path(pair.sources[k]).name
                  for k in ("image1", "image2"))
    images = _read_right(files, pair)
    return RightCamera(images[0], images[1], matrix, float(matrix[:3, 3].norm()), files,
                       intrinsics)


def _read_right(files, pair: FramePair) -> list:
    images = []
    for path in files:
        if not path.is_file():
            raise DatasetError(f"{path}: right camera frame not found (needed for stereo)")
        image = read_image(path)
        if image.shape[:2] != tuple(pair.size):
            raise DatasetError(f"{path}: right frame is {image.shape[1]}x{image.shape[0]} but the "
                               f"left frame is {pair.size[1]}x{pair.size[0]}")
        images.append(torch.from_numpy(image).permute(2, 0, 1).contiguous())
    return images
