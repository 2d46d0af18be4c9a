"""Reader of the ``custom`` layout: any RGB-D sequence with known cameras (specified in docs/datasets.md).

Layout below the root (several scenes), or the root itself as the single scene::

    SCENE/frames/0000.png         frames (8- or 16-bit PNG, or JPEG), any names (see below)
    SCENE/depth/0000.npy          depth of each frame, same stem (or number): .npy, 16-bit .png or .exr
    SCENE/cameras.json            intrinsics and one pose per frame (or cameras.txt)
    SCENE/flow/0000.flo           optional: flow from this frame to the next one (Middlebury .flo)
    SCENE/sky/0000.png            optional: the frame's sky mask (non-zero: sky), same stem

Frame order and pairs (:mod:`~weathergen.datasets.framenames`): consecutive frames in order are
the pairs. Where the names differ in one run of digits (``0000.png``, ``000012_left.png``,
``frame7.png``), that run is the frame number and sets the order; otherwise the frames are in
natural name order and numbered by position from 0. A ``frame_pattern`` (a glob such as
``*_left.png``) picks the frames among other files; frames named in several ways without one are
a problem that ``check`` explains. The camera file names frames by that number (or, in JSON, by the
frame file's stem). The split option does not apply (leave it at ``training``).

Conventions of the camera file (defaults in brackets): ``pose`` [cam_from_world] or
world_from_cam; ``axes`` [opencv] (x right, y down, z forward) or opengl (x right, y up, z backward,
as Blender and OpenGL cameras); ``depth`` [z] (camera-z distance) or range (distance along the
ray); ``depth_png_scale`` (scene units per PNG step, required for PNG depth).

Valid depth. Depth values that are zero, negative, NaN or infinite are invalid. The sky (the
frame's mask in ``sky/`` where there is one, else estimated) gets ``far_depth``; the other invalid
pixels are completed from the valid ones (:func:`~weathergen.datasets.depth.complete_depth`), or,
with ``max_gap_px`` 0, left unknown at ``far_depth``; ``depth_provenance1/2`` say which pixel is
which. A frame without any valid depth is an
error (with a hint about the sign convention when its values are negative); a frame whose valid
fraction is below ``min_valid_depth`` (default 0.5) gets a warning from ``check``.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..errors import ConfigError, DatasetError, FormatError
from ..framepair import COMPLETED, FramePair, PairId
from ..geometry import backproject, invert_rigid
from ..io.images import read_image
from ..io.custom_formats import DEPTH_SUFFIXES, CameraFile, read_camera_file, read_depth
from ..io.sintel_formats import read_flo
from .base import PairRef, Selection
from .base import WARNING, Problem
from .common import (FarDepthDataset, add_warnings, check_size, flow_warnings, read_frames,
                     require_files)
from .depth import complete_depth
from .framenames import order_frames
from .stereo import RightCamera, custom_right

#: Below this fraction of valid depth in a frame, ``check`` warns.
DEFAULT_MIN_VALID_DEPTH = 0.5
#: Gaps in the depth (sensor holes at object edges, dark or shiny surfaces) are filled up to this
#: distance (pixels) from a valid pixel by the joint-bilateral fill; larger regions that are not
#: sky are completed from the columns below them (:mod:`weathergen.datasets.depth`).
DEFAULT_MAX_GAP_PX = 24.0
#: OpenGL camera axes (y up, z backward) -> OpenCV camera axes (y down, z forward)
_CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])


class CustomDataset(FarDepthDataset):
    """Consecutive frame pairs of every scene in the ``custom`` layout."""

    name = "custom"
    split_folders = {"training": "."}
    required_files = ("image1", "image2", "cameras", "depth1", "depth2")
    options = FarDepthDataset.options + ("frame_pattern", "min_valid_depth", "max_gap_px")
    stereo = True                    # where a scene holds right/ (frames and camera.json)

    def __init__(self, root, selection: Selection = Selection(), *, frame_pattern: Optional[str] = None,
                 min_valid_depth: float = DEFAULT_MIN_VALID_DEPTH,
                 max_gap_px: float = DEFAULT_MAX_GAP_PX, **options):
        super().__init__(root, selection, **options)
        if not 0 <= min_valid_depth <= 1:
            raise ConfigError(f"minimum valid-depth fraction must be in [0, 1], got {min_valid_depth}")
        if not max_gap_px >= 0:
            raise ConfigError(f"max_gap_px must be zero or positive, got {max_gap_px}")
        self.max_gap_px = float(max_gap_px)
        self.frame_pattern = frame_pattern
        self.min_valid_depth = float(min_valid_depth)
        self._cameras = lru_cache(maxsize=8)(read_camera_file)
        self._numbers: dict[str, int] = {}      # second frame of each listed pair -> its number
        self._numbering = "name"                # how the frames of the scene last listed are numbered

    # -- listing ---------------------------------------------------------------------------------
    def right_camera(self, pair: FramePair) -> RightCamera:
        """``SCENE/right/``: its frames and ``camera.json`` (see :mod:`weathergen.datasets.stereo`)."""
        return custom_right(pair)

    def scene_dirs(self) -> dict[str, Path]:
        """Scene name -> folder. The root is the single scene when it holds ``frames/`` itself."""
        if (self.root / "frames").is_dir():
            return {self.root.resolve().name: self.root}
        found = {p.name: p for p in sorted(self.root.iterdir()) if (p / "frames").is_dir()}
        if not found:
            raise DatasetError(f"{self.root}: no scene found (expected custom layout "
                               f"ROOT/SCENE/frames/0000.png or ROOT/frames/0000.png)")
        return found

    def all_scenes(self) -> list[str]:
        return sorted(self.scene_dirs())

    def frames(self, scene_dir: Path) -> dict[int, Path]:
        """Frame number -> frame file, in order. Raises :class:`DatasetError` saying why the
        folder's images cannot be paired."""
        folder = scene_dir / "frames"
        order = order_frames([p.name for p in folder.iterdir() if p.is_file()], self.frame_pattern)
        if order.problem:
            raise DatasetError(f"{folder}: {order.problem}")
        self._numbering = order.numbering
        return {n: folder / name for n, name in order.frames}

    @staticmethod
    def _numbered_files(scene_dir: Path) -> dict[str, dict[int, Path]]:
        """Depth and flow files by frame number, for names that differ from the frames' in more
        than the number (``frame-000012.color.jpg`` with ``frame-000012.depth.png``): folder
        ("depth", "flow") -> number -> file. A folder whose files cannot be numbered by their
        names (several kinds of name, no number) gives nothing; nothing is guessed."""
        out: dict[str, dict[int, Path]] = {}
        for sub, suffixes in (("depth", DEPTH_SUFFIXES), ("flow", (".flo",))):
            folder = scene_dir / sub
            if not folder.is_dir():
                continue
            names = [p.name for p in folder.iterdir() if p.is_file() and p.suffix.lower() in suffixes]
            order = order_frames(names, "*") if len(names) >= 2 else None
            if order is not None and not order.problem and order.numbering == "name":
                out[sub] = {n: folder / name for n, name in order.frames}
        return out

    def pairs(self) -> list[PairRef]:
        dirs = self.scene_dirs()
        sel = self.selection
        refs = []
        self._listing_problems = {}
        for scene in sel.pick_scenes(list(dirs), self.root):
            try:
                frames = self.frames(dirs[scene])
            except DatasetError as exc:
                # one scene that cannot be paired does not hide the others; check reports it
                folder = str(dirs[scene] / "frames")
                self._listing_problems[scene] = [
                    Problem("frames cannot be paired: " + str(exc)[len(folder) + 2:], folder)]
                continue
            numbers = list(frames)
            by_number = self._numbered_files(dirs[scene]) if self._numbering == "name" else {}
            starts = list(zip(numbers[:-1], numbers[1:]))
            if sel.first_frame is not None:
                starts = [s for s in starts if s[0] >= sel.first_frame]
            if sel.frames_per_scene is not None:
                starts = starts[: sel.frames_per_scene]
            for a, b in starts:
                self._numbers[str(frames[b])] = b
                refs.append(PairRef(PairId(self.name, sel.split, scene, a),
                                    self._files(dirs[scene], frames[a], frames[b], (a, b), by_number)))
        if not refs and self._listing_problems:
            first = next(iter(self._listing_problems.values()))[0]
            raise DatasetError(f"{first.where}: {first.kind}")
        return refs

    def pair_warnings(self, ref: PairRef, pair: FramePair) -> list[Problem]:
        out = super().pair_warnings(ref, pair)
        for i, key in enumerate(("depth1", "depth2")):
            stats = pair.meta.get("depth_values", [{}, {}])[i]
            valid = stats.get("valid", 1.0)
            where = f"{ref.files[key]} ({100 * valid:.0f}% valid)"
            rest = ("sky or completed from the valid pixels" if self.max_gap_px > 0
                    else "sky or unknown, both at the far depth")
            if valid < self.min_valid_depth:
                out.append(Problem(f"less than {100 * self.min_valid_depth:g}% of the depth is valid "
                                   f"(the rest is {rest})", where, WARNING))
            if stats.get("negative", 0):
                out.append(Problem(_NEGATIVE_HINT, f"{ref.files[key]} "
                                   f"({100 * stats['negative']:.0f}% negative)", WARNING))
        return out

    @staticmethod
    def _files(scene_dir: Path, frame1: Path, frame2: Path, numbers: tuple = (None, None),
               by_number: Optional[dict] = None) -> dict:
        """The files of a pair: depth and flow share the frame file's stem or, failing that,
        its number (``by_number``, see :meth:`_numbered_files`)."""
        by_number = by_number or {}

        def depth_of(frame: Path, number) -> Path:
            candidates = [scene_dir / "depth" / (frame.stem + s) for s in DEPTH_SUFFIXES]
            found = next((c for c in candidates if c.exists()), None)
            return found or by_number.get("depth", {}).get(number, candidates[0])

        cams = scene_dir / "cameras.json"
        if not cams.exists() and (scene_dir / "cameras.txt").exists():
            cams = scene_dir / "cameras.txt"
        flow = scene_dir / "flow" / f"{frame1.stem}.flo"
        if not flow.exists():
            flow = by_number.get("flow", {}).get(numbers[0], flow)
        return {"image1": frame1, "image2": frame2, "depth1": depth_of(frame1, numbers[0]),
                "depth2": depth_of(frame2, numbers[1]), "cameras": cams, "flow": flow,
                "sky1": scene_dir / "sky" / f"{frame1.stem}.png",
                "sky2": scene_dir / "sky" / f"{frame2.stem}.png"}

    def missing_hint(self, key: str) -> str:
        if key in ("depth1", "depth2"):
            return (" (a depth file is the frame's name with .npy, .png or .exr in depth/, or a file "
                    "there with the frame's number, such as frame-000012.depth.png for "
                    "frame-000012.color.jpg)")
        return ""

    # -- reading ---------------------------------------------------------------------------------
    def load(self, ref: PairRef) -> FramePair:
        files = ref.files
        require_files(files, ("image1", "image2", "cameras"))
        require_files(files, ("depth1", "depth2"), self.missing_hint("depth1"))
        img1, img2, meta = read_frames(files)
        size = img1.shape[:2]
        check_size(files["image2"], "frame", img2.shape, size)

        cams: CameraFile = self._cameras(Path(files["cameras"]))
        n1, n2 = ref.id.frame, self._numbers.get(str(files["image2"]), ref.id.frame + 1)
        (e1, k1), (e2, k2) = (self._camera(cams, files["cameras"], n, Path(files[key]).stem)
                              for n, key in ((n1, "image1"), (n2, "image2")))
        if not np.allclose(k1, k2, rtol=1e-6, atol=1e-6):
            raise DatasetError(f"{files['cameras']}: frames {n1} and {n2} have different intrinsics; "
                               f"a frame pair holds one camera matrix")

        depths, provenance, values = [], [], []
        for key in ("depth1", "depth2"):
            d = read_depth(files[key], cams.depth_png_scale)
            check_size(files[key], "depth", d.shape, size)
            ok = np.isfinite(d) & (d > 0)
            with np.errstate(invalid="ignore"):
                negative = float((d < 0).mean())
            if not ok.any():
                reason = (f"{100 * negative:.0f}% of its values are negative: {_NEGATIVE_HINT}"
                          if negative else "every value is zero, NaN or infinite")
                raise DatasetError(f"{files[key]}: no valid depth in this frame; {reason}")
            if cams.depth == "range":
                d = _range_to_z(d, k1)
            sky = self._sky(files.get("sky" + key[-1]), size)
            depth, prov = complete_depth(d, ok, img1 if key == "depth1" else img2, sky=sky,
                                         far_depth=self.far_depth, max_gap_px=self.max_gap_px)
            values.append({"valid": round(float(ok.mean()), 4), "negative": round(negative, 4),
                           "filled": round(float((prov == COMPLETED).mean()), 4)})
            depths.append(depth)
            provenance.append(prov)

        flow = flow_valid = None
        if Path(files["flow"]).exists():
            fl = read_flo(files["flow"])
            check_size(files["flow"], "flow", fl.shape, size)
            # Middlebury convention: components beyond 1e9 mark unknown flow
            known = ~(np.abs(fl) >= 1e9).any(axis=2)
            flow, flow_valid = np.where(known[..., None], fl, 0).astype(np.float32), known
        flow, flow_valid, notes = flow_warnings(files["flow"], flow, flow_valid)
        add_warnings(meta, notes)

        return self.posed_pair(ref, files, (img1, img2), depths, k1, e1, e2, flow=flow,
                               flow_valid=flow_valid, provenance=provenance,
                               meta={"far_depth": self.far_depth, "pose": cams.pose,
                                     "axes": cams.axes, "depth": cams.depth,
                                     "depth_values": values, **meta})

    def describe(self) -> dict:
        out = super().describe()
        out.update(frame_pattern=self.frame_pattern, min_valid_depth=self.min_valid_depth,
                   max_gap_px=self.max_gap_px)
        return out

    @staticmethod
    def _sky(path, size) -> Optional[np.ndarray]:
        """The frame's sky mask (``SCENE/sky/STEM.png``, non-zero: sky), or None where there is none
        (the sky is then estimated). Shape: -> (H, W) bool."""
        if path is None or not Path(path).is_file():
            return None
        mask = read_image(path)
        check_size(path, "sky mask", mask.shape, size)
        return mask.max(axis=2) > 0

    @staticmethod
    def _camera(cams: CameraFile, path, number: int, stem: str) -> tuple[np.ndarray, np.ndarray]:
        """``(cam_from_world (4, 4) in OpenCV axes, intrinsics (3, 3))`` of one frame, named in the
        camera file by its stem or its number."""
        key = stem if stem in cams.frames else number
        if key not in cams.frames:
            raise FormatError(path, f"has no pose for frame {number} ({stem})")
        pose, k = cams.frames[key]
        k = k if k is not None else cams.intrinsics
        if k is None:
            raise FormatError(path, f"has no intrinsics for frame {number} (give 'intrinsics' at the top)")
        cam_from_world = pose if cams.pose == "cam_from_world" else invert_rigid(torch.from_numpy(pose)).numpy()
        if cams.axes == "opengl":
            cam_from_world = _CV_FROM_GL @ cam_from_world
        return cam_from_world, k


_NEGATIVE_HINT = ("negative depth is counted as missing; depth must be the positive camera-z distance "
                  "(if your maps store negative values, e.g. OpenGL's -z or a signed disparity, "
                  "negate them)")


def _range_to_z(distance: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Camera-z depth from distance along each pixel's ray. Shape: (H, W) -> (H, W)."""
    ones = torch.ones(1, *distance.shape, dtype=torch.float64)
    rays = backproject(ones, torch.from_numpy(k)).numpy()        # (3, H, W), z = 1
    return (distance / np.linalg.norm(rays, axis=0)).astype(np.float32)
