"""Reader of the ``custom`` layout: any RGB-D sequence with known cameras (specified in docs/datasets.md).

Layout below the root (several scenes), or the root itself as the single scene::

    SCENE/frames/0000.png         frames (8- or 16-bit PNG, or JPEG), any names (see below)
    SCENE/depth/0000.npy          depth of each frame, same stem (or number): .npy, 16-bit .png or .exr
    SCENE/cameras.json            intrinsics and one pose per frame (or cameras.txt)
    SCENE/flow/0000.flo           optional: flow from this frame to the next one (Middlebury .flo)

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

Valid depth. Depth values that are zero, negative, NaN or infinite are invalid: those within
``max_gap_px`` (default 24) of a valid pixel are filled in from their neighbours (inverse depth,
guided by the frame's colours: :func:`~weathergen.datasets.densify.fill_sparse`), the others get
``far_depth``; ``depth_measured1/2`` mark the valid pixels. A frame without any valid depth is an
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
from ..framepair import FramePair, PairId
from ..geometry import backproject, invert_rigid
from ..io.custom_formats import DEPTH_SUFFIXES, CameraFile, read_camera_file, read_depth
from ..io.sintel_formats import read_flo
from .base import PairRef, Selection
from .base import WARNING, Problem
from .common import (FarDepthDataset, add_warnings, check_size, flow_warnings, read_frames,
                     require_files)
from .densify import fill_sparse
from .framenames import order_frames
from .stereo import RightCamera, custom_right

#: Below this fraction of valid depth in a frame, ``check`` warns.
DEFAULT_MIN_VALID_DEPTH = 0.5
#: Gaps in the depth (sensor holes at object edges, dark or shiny surfaces) are filled up to this
#: distance (pixels) from a valid pixel; farther pixels get the far depth.
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
            if valid < self.min_valid_depth:
                out.append(Problem(f"less than {100 * self.min_valid_depth:g}% of the depth is valid "
                                   f"(the rest is filled in from valid pixels up to "
                                   f"{self.max_gap_px:g} px away, or gets the far depth)", where, WARNING))
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
                "depth2": depth_of(frame2, numbers[1]), "cameras": cams, "flow": flow}

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

        depths, measured, values = [], [], []
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
            depth, filled = self._fill_gaps(d, ok, img1 if key == "depth1" else img2)
            values.append({"valid": round(float(ok.mean()), 4), "negative": round(negative, 4),
                           "filled": round(float(filled.mean()), 4)})
            depths.append(depth)
            measured.append(ok)

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
                               flow_valid=flow_valid, measured=measured,
                               meta={"far_depth": self.far_depth, "pose": cams.pose,
                                     "axes": cams.axes, "depth": cams.depth,
                                     "depth_values": values, **meta})

    def describe(self) -> dict:
        out = super().describe()
        out.update(frame_pattern=self.frame_pattern, min_valid_depth=self.min_valid_depth,
                   max_gap_px=self.max_gap_px)
        return out

    def _fill_gaps(self, depth: np.ndarray, ok: np.ndarray, image: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Depth with its gaps filled: pixels within ``max_gap_px`` of a valid one get a value
        from their neighbours (inverse depth, guided by the frame's colours, as KITTI's sparse
        disparity), the rest the far depth. Shape: (H, W) each -> (depth float32, filled bool)."""
        filled = np.zeros_like(ok)
        out = np.where(ok, depth, self.far_depth).astype(np.float32)
        if ok.all() or self.max_gap_px <= 0:
            return out, filled
        inverse = np.where(ok, 1.0 / np.where(ok, depth, 1.0), 0.0).astype(np.float32)
        values, known = fill_sparse(inverse, ok, image, max_gap_px=self.max_gap_px)
        filled = known & ~ok & np.isfinite(values) & (values > 0)
        out[filled] = 1.0 / values[filled]
        return out, filled

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
