"""Spring reader: left frames, depth from the HDF5 disparity, per-frame cameras, flow where present.

Layout below the root (``SPLIT`` is ``train`` or ``test``; ``training``/``testing`` are accepted)::

    SPLIT/SCENE/frame_left/frame_left_0001.png       frames, numbered from 1
    SPLIT/SCENE/disp1_left/disp1_left_0001.dsp5      disparity of each frame (HDF5, 2x resolution)
    SPLIT/SCENE/cam_data/intrinsics.txt              fx fy cx cy per frame
    SPLIT/SCENE/cam_data/extrinsics.txt              a 4x4 matrix per frame
    SPLIT/SCENE/flow_FW_left/flow_FW_left_0001.flo5  optional: flow i -> i+1 (HDF5, 2x resolution)

Resolution. Spring stores disparity and flow at twice the frame resolution in each direction,
values in frame pixels. Each 2x2 block is reduced to one of its valid samples (the medoid,
:func:`~weathergen.io.spring_formats.reduce_2x2`), never an average that would put depth between
a foreground edge and the background. Files already at frame resolution are taken as they are;
any other size is an error naming the file.

Depth. ``depth = fx * 0.065 / disparity`` (Spring's stereo baseline is 0.065 m), in metres, from
each frame's own disparity file. Pixels whose 2x2 block has no valid disparity (NaN, zero: the sky)
are the sky: they get ``far_depth``, and the record's ``depth_provenance1/2`` say so (every other
pixel is measured: Spring's depth is dense).

Cameras. ``intrinsics.txt`` line i belongs to frame i. The record holds one camera matrix, so a
pair whose two frames have different intrinsics (a zoom) is refused. ``extrinsics.txt`` matrix i
is taken as frame i's **world-to-camera** transform in **OpenCV camera axes** (x right, y down,
z forward), i.e. ``cam_from_world`` as in Sintel's ``.cam`` files; public Spring tools invert these
matrices to obtain camera poses, which agrees. Pass ``extrinsics="camera-to-world"`` if your copy
stores the inverse. ``cam2_from_cam1 = E2 @ inverse(E1)``.

The test split has no disparity ground truth: its pairs are listed (and ``check`` runs), but
loading one fails with a message saying that the split has no depth; weather needs the train split.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import ConfigError, DatasetError
from ..framepair import MEASURED, SKY, FramePair, PairId
from ..io.spring_formats import read_dsp5, read_extrinsics_txt, read_flo5, read_intrinsics_txt, reduce_2x2
from .base import NativeFlow, PairRef, Selection, frame_numbers
from .common import (FarDepthDataset, add_warnings, check_size, flow_warnings, read_frames,
                     require_files)
from .stereo import RightCamera, rectified_right

_FRAME_RE = re.compile(r"^frame_left_(\d{4,})\.png$")
#: Distance between Spring's left and right cameras, metres.
SPRING_BASELINE = 0.065
EXTRINSICS = ("world-to-camera", "camera-to-world")


class SpringDataset(FarDepthDataset):
    """Frame pairs ``(i, i+1)`` of the left camera of every selected Spring scene."""

    name = "spring"
    split_folders = {"train": "train", "training": "train", "test": "test", "testing": "test"}
    frame_rate = 24.0                # cut from a Blender open movie made at 24 fps
    native_flow = NativeFlow("flow_FW_left", "flo5")
    stereo = True                    # frame_right, at the baseline
    options = FarDepthDataset.options + ("extrinsics", "baseline")

    def __init__(self, root, selection: Selection = Selection(), *, extrinsics: str = "world-to-camera",
                 baseline: float = SPRING_BASELINE, **options):
        super().__init__(root, selection, **options)
        if extrinsics not in EXTRINSICS:
            raise ConfigError(f"unknown Spring extrinsics convention {extrinsics!r}; choose from "
                              f"{', '.join(EXTRINSICS)}")
        if not baseline > 0:
            raise ConfigError(f"stereo baseline must be positive, got {baseline}")
        self.extrinsics = extrinsics
        self.baseline = float(baseline)

    # -- listing ---------------------------------------------------------------------------------
    def scenes(self) -> list[str]:
        if not self.split_dir.is_dir():
            raise DatasetError(f"{self.split_dir}: no such folder (expected Spring layout "
                               f"ROOT/{self.split_dir.name}/SCENE/frame_left/frame_left_0001.png)")
        return sorted(p.name for p in self.split_dir.iterdir() if (p / "frame_left").is_dir())

    def all_scenes(self) -> list[str]:
        return self.scenes()

    def frames(self, scene: str) -> list[int]:
        return frame_numbers(self.split_dir / scene / "frame_left", _FRAME_RE)

    def pairs(self) -> list[PairRef]:
        refs = []
        self._listing_problems = {}
        for scene in self.selection.pick_scenes(self.scenes(), self.split_dir):
            frames = self.frames(scene)
            self._note_gaps(scene, frames, self.split_dir / scene / "frame_left")
            for f in self.selection.pick_frames(frames):
                refs.append(PairRef(PairId(self.name, self.split_dir.name, scene, f), self._files(scene, f)))
        return refs

    def _files(self, scene: str, f: int) -> dict:
        s = self.split_dir / scene
        return {
            "image1": s / "frame_left" / f"frame_left_{f:04d}.png",
            "image2": s / "frame_left" / f"frame_left_{f + 1:04d}.png",
            "disp1": s / "disp1_left" / f"disp1_left_{f:04d}.dsp5",
            "disp2": s / "disp1_left" / f"disp1_left_{f + 1:04d}.dsp5",
            "intrinsics": s / "cam_data" / "intrinsics.txt",
            "extrinsics": s / "cam_data" / "extrinsics.txt",
            "flow": s / "flow_FW_left" / f"flow_FW_left_{f:04d}.flo5",
        }

    # -- reading ---------------------------------------------------------------------------------
    required_files = ("image1", "image2", "disp1", "disp2", "intrinsics", "extrinsics")

    def missing_hint(self, key: str) -> str:
        if self.split_dir.name == "test" and key in ("disp1", "disp2"):
            return (" (the Spring test split ships no disparity, so it has no depth and weather "
                    "cannot be placed; use the train split)")
        return ""

    def load(self, ref: PairRef) -> FramePair:
        files = ref.files
        require_files(files, ("image1", "image2"))
        require_files(files, ("disp1", "disp2"), self.missing_hint("disp1"))
        require_files(files, ("intrinsics", "extrinsics"))
        f = ref.id.frame

        img1, img2, meta = read_frames(files)
        size = img1.shape[:2]
        check_size(files["image2"], "frame", img2.shape, size)

        intr = read_intrinsics_txt(files["intrinsics"])
        ext = read_extrinsics_txt(files["extrinsics"])
        for key, table in (("intrinsics", intr), ("extrinsics", ext)):
            if len(table) < f + 1:
                raise DatasetError(f"{files[key]}: has {len(table)} frames, but frame {f + 1} is needed")
        k1, k2 = (np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
                  for fx, fy, cx, cy in (intr[f - 1], intr[f]))
        if not np.allclose(k1, k2, rtol=1e-4, atol=1e-3):
            raise DatasetError(f"{files['intrinsics']}: frames {f} and {f + 1} have different "
                               f"intrinsics (a zoom); a frame pair holds one camera matrix")
        e1, e2 = ext[f - 1], ext[f]
        if self.extrinsics == "camera-to-world":
            e1, e2 = np.linalg.inv(e1), np.linalg.inv(e2)

        depths, provenance = [], []
        for key in ("disp1", "disp2"):
            disp, ok = _at_frame_size(read_dsp5(files[key]), files[key], "disparity", size)
            ok &= np.isfinite(disp) & (disp > 0)
            depth = np.full(size, self.far_depth, np.float32)
            depth[ok] = (k1[0, 0] * self.baseline / disp[ok]).astype(np.float32)
            depths.append(depth)
            provenance.append(np.where(ok, MEASURED, SKY).astype(np.uint8))

        flow = flow_valid = None
        if Path(files["flow"]).exists():
            flow, flow_valid = _at_frame_size(read_flo5(files["flow"]), files["flow"], "flow", size)
        # the format marks invalid flow with NaN
        flow, flow_valid, notes = flow_warnings(files["flow"], flow, flow_valid,
                                                nan_marks_invalid=True)
        if flow is not None:
            flow[~flow_valid] = 0
        add_warnings(meta, notes)

        return self.posed_pair(ref, files, (img1, img2), depths, k1, e1, e2, flow=flow,
                               flow_valid=flow_valid, provenance=provenance,
                               meta={"baseline_m": self.baseline, "far_depth": self.far_depth,
                                     "extrinsics": self.extrinsics, **meta})

    def right_camera(self, pair: FramePair) -> RightCamera:
        """``frame_right``'s two frames, at the reader's ``baseline``."""
        root = self.split_dir / pair.id.scene / "frame_right"
        files = tuple(root / f"frame_right_{n:04d}.png" for n in (pair.id.frame, pair.id.frame + 1))
        return rectified_right(files, float(self.baseline), pair)

    def describe(self) -> dict:
        out = super().describe()
        out.update(extrinsics=self.extrinsics, baseline=self.baseline)
        return out


def _at_frame_size(data: np.ndarray, path, what: str, size: tuple[int, int]):
    """Ground truth at frame resolution: 2x grids reduced, 1x grids kept; anything else refused.

    Shape: data (h, w[, C]) -> ``(values (H, W[, C]) float32, valid (H, W) bool)``.
    """
    h, w = size
    finite = np.isfinite(data) if data.ndim == 2 else np.isfinite(data).all(axis=2)
    if data.shape[:2] == (2 * h, 2 * w):
        valid = finite & (data > 0) if data.ndim == 2 else finite
        return reduce_2x2(data, valid)
    if data.shape[:2] == (h, w):
        return data.astype(np.float32), finite
    raise DatasetError(f"{path}: {what} is {data.shape[1]}x{data.shape[0]} but the frame is {w}x{h}; "
                       f"expected {2 * w}x{2 * h} (Spring's ground truth) or {w}x{h}")
