"""Where one pair's files go in an output folder, and the writer of a pair's files.

Layout below the output folder ``OUT`` (``SPLIT`` as in the input, ``PASS`` the output pass name,
by default ``<preset>_<input pass>``, e.g. ``snow_clean``; ``PAIR`` is ``<scene>_<frame>`` of the
pair's first frame, e.g. ``alley_1_0001``)::

    OUT/manifest.json                         the run: resolved preset, seeds, inputs, timings
    OUT/manifest.d/shard-I-of-N.json          one part per shard, merged into manifest.json
    OUT/SPLIT/PASS/PAIR/frame_FFFF.png        augmented first frame (8-bit PNG)
    OUT/SPLIT/PASS/PAIR/frame_GGGG.png        augmented second frame, G = F + 1
    OUT/SPLIT/PASS_exr/PAIR/frame_FFFF.exr    float frames with an 'opacity' channel (--format exr/both)
    OUT/SPLIT/PASS_right/PAIR/frame_FFFF.png  the right camera's frames (--stereo: KITTI, Spring,
    OUT/SPLIT/PASS_right_exr/PAIR/...exr         custom), as the left's: PNG and/or EXR with opacity,
    OUT/SPLIT/depth_right/PAIR/frame_FFFF.dpt    its depth (warped from the left) and cameras;
    OUT/SPLIT/camdata_right/PAIR/frame_FFFF.cam  right_from_left and its intrinsics in the metadata
    OUT/SPLIT/particles/PAIR/frame_FFFF.npz   particle metadata of the pair (numpy-readable)
    OUT/SPLIT/depth/PAIR/frame_FFFF.dpt       geometry the particles were placed in, in Sintel
    OUT/SPLIT/camdata_left/PAIR/frame_FFFF.cam   formats (depth and cameras after the depth scale),
    OUT/SPLIT/depth_provenance/PAIR/frame_FFFF.png  where each depth comes from: 8-bit codes 0
                                              measured, 1 completed, 2 sky, 3 unknown (the right
                                              camera's in depth_provenance_right/)
    OUT/SPLIT/flow/PAIR/frame_FFFF.flo        and ground-truth flow where the input has it
    OUT/SPLIT/invalid/PAIR/frame_FFFF.png     non-zero where that flow is not valid (sparse flow)
    OUT/SPLIT/flow_occ/PAIR/frame_FFFF.png    the same flow in the input's own form, where its reader
    OUT/SPLIT/flow_FW_left/PAIR/frame_FFFF.flo5   declares one (``Dataset.native_flow``): KITTI's
                                              16-bit PNG, Spring's HDF5

With particle ground truth (``--particle-truth``; see :mod:`weathergen.engine.rendering.groundtruth`)::

    OUT/SPLIT/particle_flow/PAIR/frame_FFFF.flo      flow of the particle layer (opacity-weighted)
    OUT/SPLIT/particle_opacity/PAIR/frame_FFFF.png   its opacity in frame 1, 16-bit (x 65535)
    OUT/SPLIT/seen_flow/PAIR/frame_FFFF.flo          particles' flow where they dominate, scene's elsewhere
    OUT/SPLIT/seen_invalid/PAIR/frame_FFFF.png       non-zero where the seen flow is not valid
    (KITTI and Spring inputs also get particle_flow_occ / seen_flow_occ PNGs, or
    particle_flow_FW_left / seen_flow_FW_left .flo5, in their own formats)

Each pair is its own two-frame "scene", because without persistent particles the second frame of
pair ``i`` and the first frame of pair ``i + 1`` differ. The tree is therefore a Sintel tree: the
Sintel reader (and any tool that reads Sintel) reads it with ``--pass PASS``.

Every file is written atomically, and the metadata file last, so a pair whose metadata exists and
loads is complete.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..datasets import NativeFlow
from ..engine.rendering.groundtruth import seen_flow
from ..errors import FormatError
from ..framepair import FramePair, PairId
from ..io.images import write_png, write_png16
from ..io.kitti_formats import write_flow_png
from ..io.sintel_formats import write_cam, write_dpt, write_flo
from ..io.spring_formats import write_flo5
from .formats import FRAME_FORMATS, FORMATS, FrameFormat, formats_of, read_format  # noqa: F401
from .metadata import read_metadata, write_metadata

#: The largest flow magnitude (per component, pixels) a KITTI flow PNG can hold, exclusive.
KITTI_FLOW_LIMIT = 511.98
#: The file extension of each form of flow a dataset may store natively
#: (:attr:`~weathergen.datasets.Dataset.native_flow`): KITTI's 16-bit PNG, Spring's HDF5.
NATIVE_FLOW = {"kitti-png": "png", "flo5": "flo5"}
#: Outputs are Sintel trees, so input splits named otherwise (Spring's ``train``, KITTI's
#: ``testing``) get Sintel's folder name; the metadata keeps the input's own split.
SINTEL_SPLIT_FOLDER = {"train": "training", "testing": "test"}


@dataclass(frozen=True)
class RightView:
    """What a stereo render writes of the second camera, as the first camera's outputs.

    Shape: frames, opacity, depth one entry per frame written (H, W, 3) float in [0, 1], (H, W)
    float, (H, W) camera-z; intrinsics (3, 3); cam_from_world one (4, 4) per frame (the world of
    the left camera files: camera 1 where the dataset has no poses); right_from_left (4, 4).
    """

    frames: tuple
    opacity: tuple
    depth: tuple
    intrinsics: np.ndarray
    cam_from_world: tuple
    right_from_left: np.ndarray
    provenance: tuple = ()      # (H, W) uint8 per frame written, where the left view has one

    def metadata(self) -> dict[str, np.ndarray]:
        """Entries of the pair's particle metadata that place the right camera."""
        return {"right_from_left": np.asarray(self.right_from_left, np.float64),
                "right_intrinsics": np.asarray(self.intrinsics, np.float64)}


@dataclass(frozen=True)
class PairOutput:
    """Where one pair's outputs go."""

    root: Path
    split: str
    pass_name: str
    scene: str
    frame: int
    fmt: str = "png"
    geometry: bool = True
    truth: bool = False
    sequence: bool = False
    #: the input's own form of flow, written beside Sintel's (its reader's ``native_flow``)
    native: Optional[NativeFlow] = None

    @classmethod
    def of(cls, root, pair_id: PairId, pass_name: str, fmt: str = "png", geometry: bool = True,
           truth: bool = False, sequence: bool = False, native: Optional[NativeFlow] = None):
        split = SINTEL_SPLIT_FOLDER.get(pair_id.split, pair_id.split)
        return cls(Path(root), split, pass_name, pair_id.scene, pair_id.frame, fmt, geometry,
                   truth, sequence, native)

    @property
    def pair_dir(self) -> str:
        """``SCENE_FFFF`` (a two-frame scene per pair), or ``SCENE`` for a sequence render,
        whose scenes hold every frame as the input's do."""
        return self.scene if self.sequence else f"{self.scene}_{self.frame:04d}"

    def _file(self, folder: str, index: int, ext: str) -> Path:
        return self.root / self.split / folder / self.pair_dir / f"frame_{index:04d}.{ext}"

    def frame_files(self, fmt: FrameFormat | str, right: bool = False) -> tuple[Path, Path]:
        """Where frames 1 and 2 go in format ``fmt`` (a :class:`FrameFormat` or its name): the
        pass folder, suffixed ``_right`` for the right camera (``--stereo``), then the format's
        suffix (``snow_clean_right_exr``)."""
        f = FRAME_FORMATS[fmt] if isinstance(fmt, str) else fmt
        folder = f"{self.pass_name}{'_right' if right else ''}{f.folder_suffix}"
        return self._file(folder, self.frame, f.extension), self._file(folder, self.frame + 1, f.extension)

    def frame_file(self, index: int) -> Path:
        """The file a reader takes frame ``index`` (0: frame 1, 1: frame 2) from: in the output's
        first format (PNG for ``both``)."""
        return self.frame_files(read_format(self.fmt))[index]

    def read_frame(self, index: int) -> np.ndarray:
        """Weather frame ``index`` (0: frame 1, 1: frame 2) read back through its format.
        Shape: (H, W, 3) float32 in [0, 1]."""
        return read_format(self.fmt).read(self.frame_file(index))

    def stored_opacity(self, index: int) -> Optional[np.ndarray]:
        """The particles' opacity of frame ``index`` as the frame's file holds it, or None where
        the format holds none. Shape: (H, W) float32."""
        f = read_format(self.fmt)
        return None if f.read_opacity is None else f.read_opacity(self.frame_file(index))

    def frame_size(self) -> tuple[int, int]:
        """(height, width) of the weather frames, read from frame 1's file."""
        return read_format(self.fmt).size(self.frame_file(0))

    def right_geometry_files(self) -> list[Path]:
        """The right camera's depth (frames 1, 2) and camera files (frames 1, 2)."""
        return [self._file("depth_right", self.frame, "dpt"),
                self._file("depth_right", self.frame + 1, "dpt"),
                self._file("camdata_right", self.frame, "cam"),
                self._file("camdata_right", self.frame + 1, "cam")]

    def provenance_files(self, right: bool = False) -> tuple[Path, Path]:
        """The depth provenance maps of frames 1 and 2 (8-bit PNG of the class codes of
        :data:`~weathergen.framepair.PROVENANCE_NAMES`), of the right camera with ``right``."""
        folder = "depth_provenance_right" if right else "depth_provenance"
        return self._file(folder, self.frame, "png"), self._file(folder, self.frame + 1, "png")

    def right_files(self) -> list[Path]:
        """Every file a stereo render may write of the right camera (for temporary-file cleanup)."""
        frames = [p for f in FRAME_FORMATS.values() for p in self.frame_files(f, right=True)]
        return frames + self.right_geometry_files() + list(self.provenance_files(right=True))

    @property
    def metadata(self) -> Path:
        return self._file("particles", self.frame, "npz")

    def geometry_files(self, with_flow: bool) -> list[Path]:
        files = [self._file("depth", self.frame, "dpt"), self._file("depth", self.frame + 1, "dpt"),
                 self._file("camdata_left", self.frame, "cam"), self._file("camdata_left", self.frame + 1, "cam")]
        if with_flow:
            files.append(self._file("flow", self.frame, "flo"))
        return files

    @property
    def native_flow(self) -> Path | None:
        """Where the flow goes in the input's own form (KITTI, Spring), else None."""
        if self.native is None:
            return None
        return self._file(self.native.folder, self.frame, NATIVE_FLOW[self.native.format])

    @property
    def invalid_mask(self) -> Path:
        """Sintel-style mask of pixels without valid ground-truth flow (written only when some are)."""
        return self._file("invalid", self.frame, "png")

    def truth_files(self) -> dict[str, Path]:
        """Where the particle ground truth goes (see the module doc)."""
        return {"particle_flow": self._file("particle_flow", self.frame, "flo"),
                "particle_opacity": self._file("particle_opacity", self.frame, "png"),
                "seen_flow": self._file("seen_flow", self.frame, "flo"),
                "seen_invalid": self._file("seen_invalid", self.frame, "png")}

    def native_truth(self, kind: str) -> Path | None:
        """``kind`` (particle or seen) flow in the input's own form, else None."""
        if self.native is None:
            return None
        return self._file(f"{kind}_{self.native.folder}", self.frame, NATIVE_FLOW[self.native.format])

    def files(self, with_flow: bool = False) -> list[Path]:
        """Every file of this pair, the metadata file last (it marks completion)."""
        out = [p for f in formats_of(self.fmt) for p in self.frame_files(f)]
        if self.geometry:
            out += self.geometry_files(with_flow) + list(self.provenance_files())
        return out + [self.metadata]

    def listed_files(self) -> list[Path]:
        """The files the pair's metadata says were written with it (the metadata file aside).
        Raises FormatError naming the metadata file when it is missing or unreadable."""
        return [self.root / f for f in json.loads(str(read_metadata(self.metadata)["files"]))]

    def is_complete(self) -> bool:
        """True when the pair's metadata loads and every other file it lists exists."""
        if not self.metadata.exists():
            return False
        try:
            listed = self.listed_files()
        except FormatError:
            return False
        return all(p.exists() for p in listed)

    def unreadable(self) -> Optional[str]:
        """What is wrong with the pair's metadata file when it is there but cannot be read (a
        corrupt or truncated file: the pair counts as not written), else None."""
        if not self.metadata.exists():
            return None
        try:
            self.listed_files()
        except FormatError as exc:
            return str(exc)
        return None


def write_pair_outputs(out: PairOutput, pair: FramePair, frames: tuple[np.ndarray, np.ndarray],
                       opacity: tuple[np.ndarray, np.ndarray], metadata: dict[str, np.ndarray],
                       truth=None, second: bool = True, right=None) -> list[Path]:
    """Write one pair: frames, optional EXR, geometry and particle ground truth (``truth``, a
    :class:`~weathergen.engine.rendering.groundtruth.ParticleTruth`), then the metadata (last).
    ``second=False`` (a sequence's pair whose second frame the next pair writes) leaves out the
    second frame's image, EXR, depth and camera. ``right`` (a :class:`RightView`, ``--stereo``)
    adds the second camera's frames, EXR, depth and cameras, and its placement to the metadata.

    Shape: frames (H, W, 3) float in [0, 1]; opacity (H, W) float.
    """
    n = 2 if second else 1
    written = _write_frames(out, frames, opacity, n)
    if right is not None:       # the second camera: the same outputs as the first's
        written += _write_right(out, right, n)
    if out.geometry:
        depth_files = out.geometry_files(with_flow=pair.flow is not None)
        written.append(write_dpt(depth_files[0], pair.depth1[0].numpy()))
        if second:
            written.append(write_dpt(depth_files[1], pair.depth2[0].numpy()))
        k = pair.intrinsics.numpy()
        if pair.cam1_from_world is not None:
            e1, e2 = pair.cam1_from_world.numpy(), pair.cam2_from_world.numpy()
        else:   # no absolute poses: camera 1 is the world
            e1, e2 = np.eye(4), pair.cam2_from_cam1.numpy()
        written.append(write_cam(depth_files[2], k, e1))
        if second:
            written.append(write_cam(depth_files[3], k, e2))
        maps = (pair.depth_provenance1, pair.depth_provenance2)[:n]      # None: all measured
        written += [write_png(path, np.zeros(pair.size, np.uint8) if m is None else m[0].numpy())
                    for path, m in zip(out.provenance_files(), maps)]
        if pair.flow is not None:
            written.append(write_flo(depth_files[4], pair.flow.numpy().transpose(1, 2, 0)))
            if pair.flow_valid is not None and not bool(pair.flow_valid.all()):
                mask = np.where(pair.flow_valid[0].numpy(), 0, 255).astype(np.uint8)
                written.append(write_png(out.invalid_mask, mask))
            if out.native is not None:
                written.append(_write_native_flow(out.native.format, out.native_flow, pair))
    if out.truth and truth is not None:
        written += _write_truth(out, pair, truth)
    rel = [str(p.relative_to(out.root)) for p in written]
    metadata = dict(metadata)
    if right is not None:
        metadata.update(right.metadata())
    metadata["files"] = np.array(json.dumps(rel))
    write_metadata(out.metadata, metadata)
    return written + [out.metadata]


def _write_right(out: PairOutput, right: RightView, n: int) -> list[Path]:
    """The right camera's frames (PNG and/or EXR with opacity) and, with geometry, its depth and
    camera files, for the first ``n`` frames."""
    written = _write_frames(out, right.frames, right.opacity, n, right=True)
    if out.geometry:
        files = out.right_geometry_files()
        for path, depth in list(zip(files[:2], right.depth))[:n]:
            written.append(write_dpt(path, np.asarray(depth, np.float32)))
        for path, cam in list(zip(files[2:], right.cam_from_world))[:n]:
            written.append(write_cam(path, np.asarray(right.intrinsics), np.asarray(cam)))
        written += [write_png(path, np.asarray(m, np.uint8)) for path, m in
                    list(zip(out.provenance_files(right=True), right.provenance))[:n]]
    return written


def _write_frames(out: PairOutput, frames, opacity, n: int, right: bool = False) -> list[Path]:
    """The first ``n`` frames in every format of the output, format by format."""
    return [f.write(path, img, alpha) for f in formats_of(out.fmt)
            for path, img, alpha in list(zip(out.frame_files(f, right), frames, opacity))[:n]]


def _write_native_flow(fmt: str, path: Path, pair: FramePair) -> Path:
    """KITTI's 16-bit flow PNG (u, v, valid) or Spring's HDF5 ``.flo5`` (NaN where invalid)."""
    flow = pair.flow.numpy().transpose(1, 2, 0)
    valid = (np.ones(flow.shape[:2], bool) if pair.flow_valid is None
             else pair.flow_valid[0].numpy())
    if fmt == "kitti-png":
        return write_flow_png(path, flow, valid)
    return write_flo5(path, np.where(valid[..., None], flow, np.nan).astype(np.float32))


def _write_truth(out: PairOutput, pair: FramePair, truth) -> list[Path]:
    """Particle flow, opacity and seen flow (Sintel formats, plus KITTI's or Spring's own)."""
    files = out.truth_files()
    written = [write_flo(files["particle_flow"], truth.flow.numpy().transpose(1, 2, 0)),
               write_png16(files["particle_opacity"], truth.opacity[0].numpy())]
    seen, valid = seen_flow(truth, pair.flow, pair.flow_valid)
    written.append(write_flo(files["seen_flow"], seen.numpy().transpose(1, 2, 0)))
    if not bool(valid.all()):
        written.append(write_png(files["seen_invalid"],
                                 np.where(valid[0].numpy(), 0, 255).astype(np.uint8)))
    covered = truth.weight[0].numpy() > 0
    for kind, flow, ok in (("particle", truth.flow, covered), ("seen", seen, valid[0].numpy())):
        native = out.native_truth(kind)
        if native is not None:
            written.append(_write_native(out.native.format, native,
                                         flow.numpy().transpose(1, 2, 0), ok))
    return written


def _write_native(fmt: str, path: Path, flow: np.ndarray, valid: np.ndarray) -> Path:
    """A flow (H, W, 2) with its valid mask (H, W) in KITTI's PNG or Spring's ``.flo5``.

    KITTI's PNG holds flows within +-512 px; a nearer particle's larger flow is written as not
    valid there (the ``.flo`` beside it keeps the value).
    """
    if fmt == "kitti-png":
        fits = (np.abs(flow) < KITTI_FLOW_LIMIT).all(-1)
        return write_flow_png(path, np.where(fits[..., None], flow, 0.0), valid & fits)
    return write_flo5(path, np.where(valid[..., None], flow, np.nan).astype(np.float32))
