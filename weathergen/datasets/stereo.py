"""The second camera of a stereo dataset: its frames and where it sits relative to the first.

Rendering weather into a stereo rig needs, per pair, the right camera's two frames and the
transform ``right_from_left`` (rectified rigs: a translation by the baseline along -x, as the
right camera sits at +x). Where the datasets keep them:

- KITTI 2015: ``SPLIT/image_3/NNNNNN_10.png`` and ``_11.png``; the baseline from
  ``calib_cam_to_cam`` (``P_rect_02`` and ``P_rect_03``), as the reader already reads it;
- Spring: ``SPLIT/SCENE/frame_right/frame_right_FFFF.png``; the reader's baseline (0.065 m).

Baselines are multiplied by the pair's depth scale, like every other length. Other datasets have no
second camera and raise :class:`~weathergen.errors.ConfigError`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import ConfigError, DatasetError
from ..framepair import FramePair
from ..io.images import read_image

STEREO_DATASETS = ("kitti", "spring")


@dataclass
class RightCamera:
    """Shape: image1, image2 (3, H, W) float32 in [0, 1]; right_from_left (4, 4) float64."""

    image1: torch.Tensor
    image2: torch.Tensor
    right_from_left: torch.Tensor
    baseline: float
    sources: tuple


def right_camera(dataset, pair: FramePair) -> RightCamera:
    """The right camera of ``pair`` (see the module doc); DatasetError names a missing file."""
    name = pair.id.dataset
    if name == "kitti":
        root = Path(dataset.split_dir) / "image_3"
        files = (root / f"{pair.id.scene}_{pair.id.frame}.png",
                 root / f"{pair.id.scene}_{pair.id.frame + 1}.png")
        baseline = float(pair.meta["baseline_m"])
    elif name == "spring":
        root = Path(dataset.split_dir) / pair.id.scene / "frame_right"
        files = tuple(root / f"frame_right_{n:04d}.png" for n in (pair.id.frame, pair.id.frame + 1))
        baseline = float(dataset.baseline)
    else:
        raise ConfigError(f"dataset {name!r} has no second camera; stereo rendering reads "
                          f"{' and '.join(STEREO_DATASETS)} (KITTI image_3, Spring's right view)")
    images = []
    for path in files:
        if not path.is_file():
            raise DatasetError(f"{path}: right camera frame not found (needed for stereo)")
        image = read_image(path)
        if image.shape[:2] != tuple(pair.size):
            raise DatasetError(f"{path}: right frame is {image.shape[1]}x{image.shape[0]} but the "
                               f"left frame is {pair.size[1]}x{pair.size[0]}")
        images.append(torch.from_numpy(image).permute(2, 0, 1).contiguous())
    baseline *= pair.depth_scale
    right_from_left = torch.eye(4, dtype=torch.float64)
    right_from_left[0, 3] = -baseline
    return RightCamera(images[0], images[1], right_from_left, baseline, files)
