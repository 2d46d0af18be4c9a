"""Pieces the readers share: depth scaling (every reader with depth), split names and far depth
(KITTI, Spring, custom), file and size checks."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import ConfigError, DatasetError
from ..framepair import FramePair
from ..geometry import WORLD_UP_AXES, invert_rigid, to_homogeneous, up_direction
from ..io.images import read_image_kind
from .base import FILE_ROLES, Dataset, Selection
from .depth import provenance_shares

#: Depth (dataset units, metres for KITTI and Spring) given to pixels without any depth: sky,
#: and regions no measurement reaches. Far beyond where weather particles are placed.
DEFAULT_FAR_DEPTH = 1000.0


#: Which axis of a dataset's world points up: "auto" (the world axis nearest to the cameras' mean
#: up direction) or an explicit signed axis; a direction "X,Y,Z" is accepted too
#: (:func:`~weathergen.geometry.up_direction`).
WORLD_UP_CHOICES = ("auto",) + WORLD_UP_AXES


class ScaledDataset(Dataset):
    """A reader with the depth options of every command (Sintel and every reader below).

    ``depth_scale * scene_scales[scene]`` multiplies depth and camera translations, so that geometry
    stays consistent; ``camera_translation=False`` zeroes the translation between the two cameras,
    ``camera_translation="unscaled"`` only in the scenes whose scale is not 1 (the paper's research
    code's rule: it zeroes the translation of every scene it scales).
    ``world_up`` says which axis of the world (camera 1's axes where the dataset has no poses)
    points up, so that weather falls along the world's vertical; ``None`` takes the reader's
    :attr:`default_world_up`.
    """

    #: The world-up setting of this dataset when the user gives none.
    default_world_up = "auto"

    def __init__(self, root, selection: Selection = Selection(), *, depth_scale: float = 1.0,
                 scene_scales: Optional[dict[str, float]] = None,
                 camera_translation: bool | str = True,
                 world_up: Optional[str] = None, scene_scales_bundled: bool = False):
        super().__init__(root, selection)
        if not (math.isfinite(depth_scale) and depth_scale > 0):
            # an infinite or NaN scale would make every depth map look corrupt instead
            raise ConfigError(f"${{depth_scale}} must be a positive finite number, got {depth_scale}")
        world_up = self.default_world_up if world_up is None else world_up
        up_direction(world_up)          # raises ConfigError for a setting it cannot read
        self.depth_scale = float(depth_scale)
        #: where the table came from (a file, see :func:`load_scene_scales`), for messages
        self.scene_scales_source = getattr(scene_scales, "source", None) or "scene scales"
        self.scene_scales = dict(scene_scales or {})
        #: the table is one weathergen ships (its scenes need not all be in the tree)
        self.scene_scales_bundled = scene_scales_bundled or bool(getattr(scene_scales, "bundled",
                                                                         False))
        if camera_translation not in (True, False, "unscaled"):
            raise ConfigError(f"${{camera_translation}} must be true, false or 'unscaled', got "
                              f"{camera_translation!r}")
        self.camera_translation = camera_translation
        self.world_up = world_up

    def check_scene_scales(self) -> None:
        """Refuse a scene-scale entry that names no scene of the split (a typo would otherwise
        leave that scene unscaled without a word)."""
        if not self.scene_scales or self.scene_scales_bundled:
            return                      # a bundled table names scenes a tree may not hold
        scenes = self.all_scenes()
        if scenes is None:
            return
        unknown = sorted(s for s in self.scene_scales if s not in scenes)
        if unknown:
            shown = ", ".join(scenes[:12]) + (f", ... ({len(scenes)} in all)" if len(scenes) > 12 else "")
            raise ConfigError(f"{self.scene_scales_source}: no scene named {', '.join(unknown)} in "
                              f"{self.root} ({self.selection.split}); scenes there: {shown or 'none'}")

    def scale_of(self, scene: str) -> float:
        """The depth scale applied to ``scene``."""
        return self.depth_scale * self.scene_scales.get(scene, 1.0)

    def keeps_translation(self, scene: str) -> bool:
        """Whether ``scene``'s pairs keep the translation between their cameras."""
        if self.camera_translation == "unscaled":
            return self.scale_of(scene) == 1.0
        return bool(self.camera_translation)

    def posed_pair(self, ref, files: dict, images, depths, intrinsics, cam1_from_world,
                   cam2_from_world, *, flow=None, flow_valid=None, provenance=None,
                   meta: Optional[dict] = None) -> FramePair:
        """The validated record of a pair with absolute poses, the scene's depth scale applied.

        Shape: images two (H, W, 3) float in [0, 1]; depths two (H, W) in dataset units (unscaled);
        intrinsics (3, 3); poses (3, 4) or (4, 4) world-to-camera; flow (H, W, 2), flow_valid
        (H, W) bool, or None; ``provenance`` two (H, W) uint8 maps, or None: all measured
        (Sintel, the demo).
        """
        scale = self.scale_of(ref.id.scene)
        cam1, cam2, cam2_from_cam1 = scaled_poses(cam1_from_world, cam2_from_world, scale,
                                                  self.keeps_translation(ref.id.scene))
        return FramePair(
            id=ref.id,
            image1=chw(images[0]), image2=chw(images[1]),
            depth1=chw(depths[0] * np.float32(scale)), depth2=chw(depths[1] * np.float32(scale)),
            intrinsics=torch.from_numpy(np.array(intrinsics, np.float64)),
            cam2_from_cam1=cam2_from_cam1, cam1_from_world=cam1, cam2_from_world=cam2,
            flow=None if flow is None else chw(flow),
            flow_valid=None if flow_valid is None else chw(flow_valid),
            depth_provenance1=None if provenance is None else chw(provenance[0]),
            depth_provenance2=None if provenance is None else chw(provenance[1]),
            sources={k: Path(v) for k, v in files.items() if Path(v).exists()},
            depth_scale=scale, frame_rate=self.frame_rate,
            meta={**(meta or {}), **provenance_meta(provenance)},
        ).validate()

    def describe(self) -> dict:
        out = super().describe()
        out.update(depth_scale=self.depth_scale, scene_scales=self.scene_scales,
                   camera_translation=self.camera_translation, world_up=self.world_up)
        if self.scene_scales_bundled:
            out["scene_scales_bundled"] = True
        return out


def provenance_meta(provenance) -> dict:
    """``{"depth_provenance": [shares of frame 1, of frame 2]}`` for a pair's ``meta`` (and so
    the manifest), or nothing for depth measured everywhere (``provenance`` None)."""
    if provenance is None:
        return {}
    return {"depth_provenance": [provenance_shares(p) for p in provenance]}


class FarDepthDataset(ScaledDataset):
    """A reader whose depth may have pixels without a value (KITTI, Spring, custom).

    ``far_depth`` (in the dataset's units, before scaling) is the depth of the sky (and of
    pixels left unknown); the record's ``depth_provenance1/2`` say where each depth comes from
    (:mod:`weathergen.datasets.depth`). One rendering pass; splits by ``split_folders``.
    """

    #: Names the ``--split`` option accepts, mapped to the folder below the root.
    split_folders: dict[str, str] = {}
    dense_depth = False
    options = ("far_depth",)
    #: How far from a measurement gaps are filled (readers that complete depth set it; 0: none).
    max_gap_px: Optional[float] = None

    def __init__(self, root, selection: Selection = Selection(), *, far_depth: Optional[float] = None,
                 **scaling):
        super().__init__(root, selection, **scaling)
        if selection.split not in self.split_folders:
            raise ConfigError(f"unknown {self.name} split {selection.split!r}; choose from "
                              f"{', '.join(sorted(self.split_folders))}")
        if selection.pass_ != "clean":
            raise ConfigError(f"{self.name} has a single rendering pass; ${{pass_}} {selection.pass_!r} "
                              f"does not apply (leave it at 'clean')")
        far = DEFAULT_FAR_DEPTH if far_depth is None else far_depth
        if not (np.isfinite(far) and far > 0):
            raise ConfigError(f"${{far_depth}} must be a positive finite number, got {far_depth}")
        self.far_depth = float(far)

    @property
    def split_dir(self) -> Path:
        return self.root / self.split_folders[self.selection.split]

    def describe(self) -> dict:
        out = super().describe()
        out.update(far_depth=self.far_depth)
        return out

    def scene_notes(self) -> list[str]:
        """The scenes' notes, and the one line of ``max_gap_px`` 0 (``--fill-gaps 0``): what the
        pixels it leaves unfilled do."""
        notes = super().scene_notes()
        if self.max_gap_px == 0:
            notes.append(f"--fill-gaps 0: no depth is completed; pixels without a measurement that "
                         f"are not sky stay unknown at the far depth ({self.far_depth:g}), so fog "
                         f"there shows its full airlight and every particle is drawn in front of them")
        return notes

    def pair_notes(self, pair: FramePair) -> list[str]:
        """The share of each depth provenance class in each frame of ``pair``."""
        shares = pair.meta.get("depth_provenance")
        if not shares:
            return []
        return ["depth " + "; ".join(f"frame {i}: " + ", ".join(f"{name} {100 * share:.1f}%"
                                                                for name, share in s.items())
                                     for i, s in enumerate(shares, start=1))]


def read_frames(files: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    """Both frames of a pair (``files["image1"]``, ``files["image2"]``) as RGB, and facts for the
    record's ``meta``: ``{"warnings": [...]}`` when one frame is grey and the other colour (both
    are read as RGB, a grey frame replicated, so the pair reads, but no camera gives such a pair:
    a frame from another folder or pass, or a converted file). Shape: (H, W, 3) float32 each.
    """
    (img1, kind1), (img2, kind2) = read_image_kind(files["image1"]), read_image_kind(files["image2"])
    meta = {}
    if kind1 != kind2:
        meta["warnings"] = [f"{files['image2']}: the second frame is {kind2} but the first "
                            f"({Path(files['image1']).name}) is {kind1}; both are read as RGB "
                            f"(grey replicated to three channels)"]
    return img1, img2, meta


def flow_warnings(path, flow, valid, *, nan_marks_invalid: bool = False
                  ) -> tuple[Optional[np.ndarray], Optional[np.ndarray], list[str]]:
    """A pair's ground-truth flow checked, with warnings for the record's ``meta``: values that
    are not finite are marked invalid (and set to 0) and, unless the format uses NaN to mark
    invalid flow (``nan_marks_invalid``), said; a flow without any valid value is said; a
    missing flow file (``flow`` None) is said when its folder holds other flow files of its
    kind (the pair is then written without flow). Returns ``(flow, valid, warnings)``.
    Shape: flow (H, W, 2) float, valid (H, W) bool."""
    if flow is None:
        folder = Path(path).parent
        if folder.is_dir() and any(folder.glob(f"*{Path(path).suffix}")):
            return None, None, [f"{path}: ground-truth flow file is missing (the scene's other "
                                "pairs have one); the pair is written without flow"]
        return None, None, []
    valid = np.ones(flow.shape[:2], bool) if valid is None else valid
    finite = np.isfinite(flow).all(axis=2)
    bad = int((~finite).sum())
    if bad:
        flow = np.where(finite[..., None], flow, 0).astype(np.float32)
        valid = valid & finite
    said = f" ({bad} of {finite.size} not finite)" if bad and not nan_marks_invalid else ""
    if not valid.any():
        return flow, valid, [f"{path}: the ground-truth flow has no valid vector{said}; it is "
                             "written as invalid everywhere"]
    if said:
        return flow, valid, [f"{path}: {bad} of {finite.size} ground-truth flow vectors are not "
                             "finite; they are written as invalid"]
    return flow, valid, []


def add_warnings(meta: dict, warnings: list[str]) -> dict:
    """``meta`` with ``warnings`` added to its ``"warnings"`` list (which the commands print)."""
    if warnings:
        meta["warnings"] = [*meta.get("warnings", []), *warnings]
    return meta


def require_files(files: dict, keys: tuple[str, ...], hint: str = "") -> None:
    """Raise :class:`DatasetError` naming the first of ``files[key]`` that does not exist."""
    for key in keys:
        path = files.get(key)
        if path is None or not Path(path).exists():
            raise DatasetError(f"{path}: {FILE_ROLES.get(key, key)} file is missing{hint}")


def check_size(path, what: str, shape: tuple, expected: tuple) -> None:
    """Raise a one-line :class:`DatasetError` when a ``(H, W)`` map does not match the frame."""
    if tuple(shape[:2]) != tuple(expected):
        raise DatasetError(f"{path}: {what} is {shape[1]}x{shape[0]} but the frame is "
                           f"{expected[1]}x{expected[0]}")


def chw(a: np.ndarray) -> torch.Tensor:
    """(H, W, C) or (H, W) numpy -> (C, H, W) / (1, H, W) tensor."""
    a = a[..., None] if a.ndim == 2 else a
    return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1)))


def scaled_motion(cam2_from_cam1: np.ndarray, scale: float, keep_translation: bool) -> torch.Tensor:
    """``cam2_from_cam1`` with its translation scaled (or zeroed). Shape: (4, 4) -> (4, 4) float64."""
    out = torch.from_numpy(np.array(cam2_from_cam1, np.float64))
    out[:3, 3] = out[:3, 3] * scale if keep_translation else 0
    return out


def scaled_poses(cam1_from_world: np.ndarray, cam2_from_world: np.ndarray, scale: float,
                 keep_translation: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Absolute poses after a depth scale, and the relative motion between them.

    Translations are multiplied by ``scale`` so the cameras stay consistent with the scaled depth.
    Without ``keep_translation`` the motion between the two cameras is a pure rotation and frame 2's
    pose is recomputed from it.
    Shape: (4, 4) or (3, 4) each -> ``(cam1_from_world, cam2_from_world, cam2_from_cam1)``, (4, 4)
    float64.
    """
    poses = []
    for e in (cam1_from_world, cam2_from_world):
        t = torch.from_numpy(np.array(e, np.float64))
        t = to_homogeneous(t) if t.shape == (3, 4) else t
        t[:3, 3] *= scale
        poses.append(t)
    cam1, cam2 = poses
    cam2_from_cam1 = cam2 @ invert_rigid(cam1)
    if not keep_translation:
        cam2_from_cam1[:3, 3] = 0
        cam2 = cam2_from_cam1 @ cam1
    return cam1, cam2, cam2_from_cam1
