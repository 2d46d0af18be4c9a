"""Reader of the ``custom`` layout: any RGB-D sequence with known cameras (specified in docs/datasets.md).

Layout below the root (several scenes), or the root itself as the single scene::

    SCENE/frames/0000.png         frames (8- or 16-bit PNG); the stem ends in the frame number
    SCENE/depth/0000.npy          depth of each frame, same stem: .npy, 16-bit .png or .exr
    SCENE/cameras.json            intrinsics and one pose per frame (or cameras.txt)
    SCENE/flow/0000.flo           optional: flow from this frame to the next one (Middlebury .flo)

Frame pairs are consecutive frames in numeric order (the numbers need not be contiguous). The
split option does not apply (leave it at ``training``).

Conventions of the camera file (defaults in brackets): ``pose`` [cam_from_world] or
world_from_cam; ``axes`` [opencv] (x right, y down, z forward) or opengl (x right, y up, z backward,
as Blender and OpenGL cameras); ``depth`` [z] (camera-z distance) or range (distance along the
ray); ``depth_png_scale`` (scene units per PNG step, required for PNG depth). Depth values that are
0, NaN or infinite count as missing and get ``far_depth``; ``depth_measured1/2`` mark the rest.
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from ..errors import DatasetError, FormatError
from ..framepair import FramePair, PairId
from ..geometry import backproject, invert_rigid
from ..io.custom_formats import DEPTH_SUFFIXES, CameraFile, read_camera_file, read_depth
from ..io.images import read_image
from ..io.sintel_formats import read_flo
from .base import PairRef, Selection
from .common import FarDepthDataset, check_size, require_files

_FRAME_RE = re.compile(r"^(.*?)(\d+)\.png$", re.IGNORECASE)
#: OpenGL camera axes (y up, z backward) -> OpenCV camera axes (y down, z forward)
_CV_FROM_GL = np.diag([1.0, -1.0, -1.0, 1.0])


class CustomDataset(FarDepthDataset):
    """Consecutive frame pairs of every scene in the ``custom`` layout."""

    name = "custom"
    split_folders = {"training": "."}

    def __init__(self, root, selection: Selection = Selection(), **options):
        super().__init__(root, selection, **options)
        self._cameras = lru_cache(maxsize=8)(read_camera_file)

    # -- listing ---------------------------------------------------------------------------------
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
        """Frame number -> frame file. Two files with one number are an error."""
        out: dict[int, Path] = {}
        for p in sorted((scene_dir / "frames").iterdir()):
            m = _FRAME_RE.match(p.name)
            if not m:
                continue
            n = int(m.group(2))
            if n in out:
                raise DatasetError(f"{p}: frame number {n} is also used by {out[n].name}")
            out[n] = p
        return out

    def pairs(self) -> list[PairRef]:
        dirs = self.scene_dirs()
        sel = self.selection
        refs = []
        for scene in sel.pick_scenes(list(dirs), self.root):
            frames = self.frames(dirs[scene])
            numbers = sorted(frames)
            starts = list(zip(numbers[:-1], numbers[1:]))
            if sel.first_frame is not None:
                starts = [s for s in starts if s[0] >= sel.first_frame]
            if sel.frames_per_scene is not None:
                starts = starts[: sel.frames_per_scene]
            for a, b in starts:
                refs.append(PairRef(PairId(self.name, sel.split, scene, a),
                                    self._files(dirs[scene], frames[a], frames[b])))
        return refs

    @staticmethod
    def _files(scene_dir: Path, frame1: Path, frame2: Path) -> dict:
        def depth_of(frame: Path) -> Path:
            candidates = [scene_dir / "depth" / (frame.stem + s) for s in DEPTH_SUFFIXES]
            return next((c for c in candidates if c.exists()), candidates[0])

        cams = scene_dir / "cameras.json"
        if not cams.exists() and (scene_dir / "cameras.txt").exists():
            cams = scene_dir / "cameras.txt"
        return {"image1": frame1, "image2": frame2, "depth1": depth_of(frame1),
                "depth2": depth_of(frame2), "cameras": cams,
                "flow": scene_dir / "flow" / f"{frame1.stem}.flo"}

    # -- reading ---------------------------------------------------------------------------------
    def load(self, ref: PairRef) -> FramePair:
        files = ref.files
        require_files(files, ("image1", "image2", "cameras", "depth1", "depth2"))
        img1, img2 = read_image(files["image1"]), read_image(files["image2"])
        size = img1.shape[:2]
        check_size(files["image2"], "frame", img2.shape, size)

        cams: CameraFile = self._cameras(Path(files["cameras"]))
        n1, n2 = (int(_FRAME_RE.match(Path(files[k]).name).group(2)) for k in ("image1", "image2"))
        (e1, k1), (e2, k2) = (self._camera(cams, files["cameras"], n) for n in (n1, n2))
        if not np.allclose(k1, k2, rtol=1e-6, atol=1e-6):
            raise DatasetError(f"{files['cameras']}: frames {n1} and {n2} have different intrinsics; "
                               f"a frame pair holds one camera matrix")

        depths, measured = [], []
        for key in ("depth1", "depth2"):
            d = read_depth(files[key], cams.depth_png_scale)
            check_size(files[key], "depth", d.shape, size)
            ok = np.isfinite(d) & (d > 0)
            if cams.depth == "range":
                d = _range_to_z(d, k1)
            depths.append(np.where(ok, d, self.far_depth).astype(np.float32))
            measured.append(ok)

        flow = flow_valid = None
        if Path(files["flow"]).exists():
            fl = read_flo(files["flow"])
            check_size(files["flow"], "flow", fl.shape, size)
            # Middlebury convention: components beyond 1e9 mark unknown flow
            ok = np.isfinite(fl).all(axis=2) & (np.abs(fl) < 1e9).all(axis=2)
            fl = np.where(ok[..., None], fl, 0).astype(np.float32)
            flow, flow_valid = fl, ok

        return self.posed_pair(ref, files, (img1, img2), depths, k1, e1, e2, flow=flow,
                               flow_valid=flow_valid, measured=measured,
                               meta={"far_depth": self.far_depth, "pose": cams.pose,
                                     "axes": cams.axes, "depth": cams.depth})

    @staticmethod
    def _camera(cams: CameraFile, path, number: int) -> tuple[np.ndarray, np.ndarray]:
        """``(cam_from_world (4, 4) in OpenCV axes, intrinsics (3, 3))`` of one frame."""
        if number not in cams.frames:
            raise FormatError(path, f"has no pose for frame {number}")
        pose, k = cams.frames[number]
        k = k if k is not None else cams.intrinsics
        if k is None:
            raise FormatError(path, f"has no intrinsics for frame {number} (give 'intrinsics' at the top)")
        cam_from_world = pose if cams.pose == "cam_from_world" else invert_rigid(torch.from_numpy(pose)).numpy()
        if cams.axes == "opengl":
            cam_from_world = _CV_FROM_GL @ cam_from_world
        return cam_from_world, k


def _range_to_z(distance: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Camera-z depth from distance along each pixel's ray. Shape: (H, W) -> (H, W)."""
    ones = torch.ones(1, *distance.shape, dtype=torch.float64)
    rays = backproject(ones, torch.from_numpy(k)).numpy()        # (3, H, W), z = 1
    return (distance / np.linalg.norm(rays, axis=0)).astype(np.float32)
