"""MPI-Sintel reader.

Layout below the root (``SPLIT`` is ``training`` or ``test``, ``PASS`` is ``clean`` or ``final``, or
any other folder of frames, such as the weather passes ``weathergen render`` writes)::

    SPLIT/PASS/SCENE/frame_0001.png         frames, numbered from 1
    SPLIT/depth/SCENE/frame_0001.dpt        camera-z depth (training only)
    SPLIT/camdata_left/SCENE/frame_0001.cam intrinsics + world-to-camera extrinsic (training only)
    SPLIT/flow/SCENE/frame_0001.flo         flow from frame i to i+1 (training only)
    SPLIT/invalid/SCENE/frame_0001.png      optional: non-zero where flow is not to be evaluated

Scene scale: Sintel's scenes are modelled at very different world scales, while the weather model
places particles in a fixed volume of scene units. The reader multiplies each scene's depth (and the
camera translations, so that geometry stays consistent) by ``depth_scale * scene_scales[scene]``.
Both default to 1. The authors' research code used a hand-made per-scene table (for example
mountain_1 x0.05, market_2 x0.2, ambush_7 x7); pass such a table as a TOML or JSON file of
``scene = factor`` entries if you want the same look (``research`` names that table, bundled).
``camera_translation=False`` zeroes the translation between the two cameras, keeping the rotation;
``camera_translation="unscaled"`` zeroes it in the scenes whose depth is scaled only, which is what
that research code did.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from collections import Counter
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DatasetError
from ..framepair import FramePair, PairId
from ..io.images import read_raw
from ..io.sintel_formats import read_cam, read_dpt, read_flo
from ..io.text import read_text_file
from .base import PairRef, Selection, frame_numbers
from .common import ScaledDataset, add_warnings, flow_warnings, read_frames

_FRAME_RE = re.compile(r"^frame_(\d{4,})\.png$")
SPLITS = ("training", "test")
#: Folders beside the passes that hold something else than frames.
_NOT_PASSES = {"depth", "camdata_left", "flow", "flow_viz", "invalid", "occlusions", "particles"}


class SceneScales(dict):
    """A per-scene depth-scale table (scene -> factor) that remembers the file it came from.
    ``bundled``: a table shipped with weathergen (its scenes need not all be in a tree)."""

    source: str = "scene scales"
    bundled: bool = False


#: Tables shipped with weathergen, by the name ``--scene-scales`` takes: ``research``, the
#: per-scene factors of the paper's research code (``datasets/scales/research.toml``).
BUNDLED_SCALES = {"research": Path(__file__).resolve().parent / "scales" / "research.toml"}


def load_scene_scales(path: str | Path) -> dict[str, float]:
    """Read a per-scene depth-scale table (TOML or JSON object of ``scene: factor``), or a bundled
    one by name (:data:`BUNDLED_SCALES`: ``research``) where no file of that name exists.

    Returns a :class:`SceneScales` dictionary whose ``source`` is the file, so that readers name it
    when an entry names no scene of the dataset.
    """
    bundled = str(path) in BUNDLED_SCALES and not Path(path).exists()
    path = BUNDLED_SCALES[str(path)] if bundled else Path(path)
    text = read_text_file(path, "scene-scale table")
    try:
        table = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: not a valid {path.suffix.lstrip('.') or 'TOML'} table ({exc})") from None
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: expected a table of scene = factor entries, "
                          f"got a JSON {type(table).__name__}")
    out = SceneScales()
    out.source = str(path)
    out.bundled = bundled
    for scene, value in table.items():
        if (isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0
                or not math.isfinite(value)):
            raise ConfigError(f"{path}: scale of scene {scene!r} must be a positive finite number, "
                              f"got {value!r}")
        out[str(scene)] = float(value)
    return out


class SintelDataset(ScaledDataset):
    """Frame pairs ``(i, i+1)`` of every selected Sintel scene, with depth and cameras."""

    name = "sintel"
    required_files = ("image1", "image2", "depth1", "depth2", "cam1", "cam2")
    frame_rate = 24.0                # cut from Blender open movies made at 24 fps
    single_pass = False              # clean and final (and whichever other passes a tree holds)

    def __init__(self, root, selection: Selection = Selection(), **scaling):
        super().__init__(root, selection, **scaling)
        if selection.split not in SPLITS:
            raise ConfigError(f"unknown Sintel split {selection.split!r}; choose from {', '.join(SPLITS)}")

    # -- listing ---------------------------------------------------------------------------------
    @property
    def split_dir(self) -> Path:
        return self.root / self.selection.split

    @property
    def image_dir(self) -> Path:
        return self.split_dir / self.selection.pass_

    def scenes(self) -> list[str]:
        """All scene folders of the selected split and pass, sorted."""
        if not self.image_dir.is_dir() and self.split_dir.is_dir():
            passes = sorted(p.name for p in self.split_dir.iterdir()
                            if p.is_dir() and p.name not in _NOT_PASSES and not p.name.endswith("_exr"))
            raise ConfigError(f"{self.split_dir}: no pass named {self.selection.pass_!r}; "
                              f"available: {', '.join(passes) or 'none'}")
        if not self.image_dir.is_dir():
            raise DatasetError(
                f"{self.image_dir}: no such folder (expected Sintel layout "
                f"ROOT/{self.selection.split}/{self.selection.pass_}/SCENE/frame_0001.png)")
        return sorted(p.name for p in self.image_dir.iterdir() if p.is_dir() and not p.name.startswith("."))

    def all_scenes(self) -> list[str]:
        return self.scenes()

    def frames(self, scene: str) -> list[int]:
        return frame_numbers(self.image_dir / scene, _FRAME_RE)

    def pairs(self) -> list[PairRef]:
        refs = []
        self._listing_problems = {}
        for scene in self.selection.pick_scenes(self.scenes(), self.image_dir):
            frames = self.frames(scene)
            self._note_gaps(scene, frames, self.image_dir / scene)
            present = set(frames)
            if not any(f + 1 in present for f in frames):
                # a scene folder the selection names but that holds no pair would otherwise vanish
                found = ("no frame_NNNN.png files" if not frames else f"only frame {frames[0]}"
                         if len(frames) == 1 else "no two consecutive frames")
                raise DatasetError(f"{self.image_dir / scene}: scene folder holds no frame pair "
                                   f"({found}); remove it or leave it out with --scenes")
            for f in self.selection.pick_frames(frames):
                refs.append(PairRef(PairId(self.name, self.selection.split, scene, f),
                                    self._files(scene, f)))
        return refs

    def _files(self, scene: str, f: int) -> dict:
        s = self.split_dir
        name = lambda i, ext: f"frame_{i:04d}.{ext}"  # noqa: E731
        return {
            "image1": self.image_dir / scene / name(f, "png"),
            "image2": self.image_dir / scene / name(f + 1, "png"),
            "depth1": s / "depth" / scene / name(f, "dpt"),
            "depth2": s / "depth" / scene / name(f + 1, "dpt"),
            "cam1": s / "camdata_left" / scene / name(f, "cam"),
            "cam2": s / "camdata_left" / scene / name(f + 1, "cam"),
            "flow": s / "flow" / scene / name(f, "flo"),
            "invalid": s / "invalid" / scene / name(f, "png"),
        }

    # -- reading ---------------------------------------------------------------------------------
    def missing_hint(self, key: str) -> str:
        if self.selection.split == "test" and key in ("depth1", "depth2", "cam1", "cam2"):
            return " (the Sintel test split ships no depth or camera files, which weather needs)"
        return ""

    def load(self, ref: PairRef) -> FramePair:
        files = ref.files
        for key in ("depth1", "depth2", "cam1", "cam2"):
            if not Path(files[key]).exists():
                hint = self.missing_hint(key)
                raise DatasetError(f"{files[key]}: {'depth' if 'depth' in key else 'camera'} "
                                   f"file is missing{hint}")
        img1, img2, meta = read_frames(files)
        raw_depths = [read_dpt(files["depth1"]), read_dpt(files["depth2"])]
        h, w = _common_size(files, {"image1": img1.shape[:2], "image2": img2.shape[:2],
                                    "depth1": raw_depths[0].shape, "depth2": raw_depths[1].shape})
        depths = []
        for key, d in zip(("depth1", "depth2"), raw_depths):
            if not np.isfinite(d).all():
                raise DatasetError(f"{files[key]}: depth has non-finite values")
            if not (d > 0).all():
                raise DatasetError(f"{files[key]}: depth has zero or negative values")
            depths.append(d)
        k1, e1 = read_cam(files["cam1"])
        _, e2 = read_cam(files["cam2"])

        flow = valid = None
        if Path(files["flow"]).exists():
            fl = read_flo(files["flow"])
            if fl.shape[:2] != (h, w):
                raise DatasetError(f"{files['flow']}: flow is {fl.shape[1]}x{fl.shape[0]} "
                                   f"but the image is {w}x{h}")
            flow, valid = fl, np.ones((h, w), bool)
            if Path(files["invalid"]).exists():
                inv = read_raw(files["invalid"])
                if inv.shape[:2] != (h, w):
                    raise DatasetError(f"{files['invalid']}: mask is {inv.shape[1]}x{inv.shape[0]} "
                                       f"but the image is {w}x{h}")
                if inv.ndim == 3:
                    inv = inv.max(axis=2)
                valid = inv == 0
        flow, valid, notes = flow_warnings(files["flow"], flow, valid)

        return self.posed_pair(ref, files, (img1, img2), depths, k1, e1, e2, flow=flow,
                               flow_valid=valid, meta=add_warnings(meta, notes))


def _common_size(files: dict, sizes: dict) -> tuple[int, int]:
    """The ``(H, W)`` the frames and depth maps of a pair share; raise naming the odd file out.

    The size most of the four files have is taken as right (the first frame's on a tie), so the
    message names the file that differs, whichever of the four it is.
    """
    reference = Counter(sizes.values()).most_common(1)[0][0]
    for key, size in sizes.items():
        if size != reference:
            kind = "depth" if key.startswith("depth") else "frame"
            others = "the other frame and the depth maps are" if kind == "frame" else "the image is"
            raise DatasetError(f"{files[key]}: {kind} is {size[1]}x{size[0]} but {others} "
                               f"{reference[1]}x{reference[0]}")
    return reference
