"""The frame-pair record every dataset reader returns, and the conventions of the whole package.

Conventions (stated once here; docstrings elsewhere repeat them as ``Shape:`` lines)
------------------------------------------------------------------------------------
- **Images**: ``(3, H, W)`` per pair, ``(B, 3, H, W)`` in batches; RGB; ``float32`` in ``[0, 1]``.
- **Depth**: ``(1, H, W)`` / ``(B, 1, H, W)``; ``float32``; the camera-z distance (not the ray
  length) of the surface seen at each pixel, in scene units after the reader's depth scale;
  finite and strictly positive everywhere.
- **Flow**: ``(2, H, W)`` / ``(B, 2, H, W)``; ``float32``; pixels; channel 0 is ``u`` (towards +x,
  right), channel 1 is ``v`` (towards +y, down); ``p2 = p1 + flow(p1)``.
- **Valid masks**: ``(1, H, W)`` / ``(B, 1, H, W)``; ``bool``.
- **Depth provenance** (``depth_provenance1/2``): ``(1, H, W)`` ``uint8``, where each pixel's depth
  comes from: :data:`MEASURED` (0, read from the dataset), :data:`COMPLETED` (1, estimated from
  measurements by the reader), :data:`SKY` (2, the sky: the far depth), :data:`UNKNOWN` (3, no
  measurement and no completion: the far depth too); ``None`` means every pixel was measured.
  ``depth_measured1/2`` are the ``bool`` masks of its :data:`MEASURED` pixels.
- **Pixel coordinates**: ``x`` to the right, ``y`` down, the centre of the top-left pixel at
  ``(0, 0)`` (so the image spans ``[-0.5, W - 0.5]``).
- **Camera axes** (OpenCV): +x right, +y down, +z forward, along the optical axis.
- **Intrinsics**: ``(3, 3)`` / ``(B, 3, 3)``, ``float64``; ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``,
  so a camera point ``X`` lands on pixel ``(fx X/Z + cx, fy Y/Z + cy)``.
- **Rigid transforms**: ``(4, 4)`` / ``(B, 4, 4)``, ``float64``, homogeneous, named for what they
  map: ``cam2_from_cam1 @ [X1; 1] = [X2; 1]``; ``cam_from_world`` is a world-to-camera extrinsic
  (Sintel's ``.cam`` matrix ``E`` with ``x = K E X``).

Frame-pair identity: ``(dataset, split, scene, frame)`` where ``frame`` is the number of the first
frame of the pair as it appears in the dataset's file names (Sintel counts from 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Optional

import torch

from .errors import DatasetError, ShapeError

#: Depth provenance classes (``uint8`` codes of ``depth_provenance1/2``), and their names.
MEASURED, COMPLETED, SKY, UNKNOWN = 0, 1, 2, 3
PROVENANCE_NAMES = ("measured", "completed", "sky", "unknown")


def _extremes(t: torch.Tensor) -> tuple[float, float]:
    """``(min, max)`` of a tensor in one pass (NaN if it holds any NaN); ``(1, 1)`` when empty
    (every check on its values then passes, as for ``all()`` of nothing)."""
    if t.numel() == 0:
        return 1.0, 1.0
    lo, hi = torch.aminmax(t.detach())
    if torch.isnan(lo) or torch.isnan(hi):
        return math.nan, math.nan
    return float(lo), float(hi)


@dataclass(frozen=True, order=True)
class PairId:
    """Which frame pair this is: dataset, split, scene and the number of its first frame."""

    dataset: str
    split: str
    scene: str
    frame: int

    def __str__(self) -> str:
        return f"{self.dataset}/{self.split}/{self.scene}/{self.frame:04d}"

    @property
    def key(self) -> str:
        """A stable string used to derive per-pair seeds and output names."""
        return f"{self.dataset}:{self.split}:{self.scene}:{self.frame}"


@dataclass
class FramePair:
    """Two consecutive frames with depth, cameras and (optionally) ground-truth flow.

    Shape:
        image1, image2: (3, H, W) float32 RGB in [0, 1].
        depth1, depth2: (1, H, W) float32, camera-z, scene units, > 0.
        intrinsics: (3, 3) float64, shared by both frames.
        cam2_from_cam1: (4, 4) float64.
        cam1_from_world, cam2_from_world: (4, 4) float64 where the dataset has absolute poses.
        flow: (2, H, W) float32 pixels, frame 1 to frame 2, where the dataset has it.
        flow_valid: (1, H, W) bool, where ``flow`` is given.
        depth_provenance1, depth_provenance2: (1, H, W) uint8, where each depth comes from
            (:data:`MEASURED`, :data:`COMPLETED`, :data:`SKY`, :data:`UNKNOWN`); None when every
            pixel was measured.
    """

    id: PairId
    image1: torch.Tensor
    image2: torch.Tensor
    depth1: torch.Tensor
    depth2: torch.Tensor
    intrinsics: torch.Tensor
    cam2_from_cam1: torch.Tensor
    cam1_from_world: Optional[torch.Tensor] = None
    cam2_from_world: Optional[torch.Tensor] = None
    flow: Optional[torch.Tensor] = None
    flow_valid: Optional[torch.Tensor] = None
    depth_provenance1: Optional[torch.Tensor] = None
    depth_provenance2: Optional[torch.Tensor] = None
    # Which files this pair came from (for messages and manifests), e.g. {"image1": Path(...)}.
    sources: dict = field(default_factory=dict)
    # The depth scale that was applied to the stored depth (and camera translations).
    depth_scale: float = 1.0
    # Frames per second of the dataset the pair comes from (its reader's ``frame_rate``); None for
    # a pair built in code. A weather field moves its particles ``velocity / frame_rate`` a frame.
    frame_rate: Optional[float] = None
    # Plain-data facts the reader wants recorded in manifests, e.g. the residual of an estimated
    # camera motion ({"camera_motion": {"method": "opencv-pnp-ransac+lm", "rms_px": 0.3, ...}}).
    meta: dict = field(default_factory=dict)

    @property
    def size(self) -> tuple[int, int]:
        """``(H, W)`` of the frames."""
        return int(self.image1.shape[-2]), int(self.image1.shape[-1])

    @property
    def depth_measured1(self) -> Optional[torch.Tensor]:
        """(1, H, W) bool: True where frame 1's depth was measured; None when every pixel was."""
        return None if self.depth_provenance1 is None else self.depth_provenance1 == MEASURED

    @property
    def depth_measured2(self) -> Optional[torch.Tensor]:
        """(1, H, W) bool: True where frame 2's depth was measured; None when every pixel was."""
        return None if self.depth_provenance2 is None else self.depth_provenance2 == MEASURED

    def validate(self) -> "FramePair":
        """Check shapes, dtypes and values; raise :class:`DatasetError` naming the pair's files."""
        h, w = self.size
        where = self.sources.get("image1", self.id)

        def fail(msg: str):
            raise DatasetError(f"{where}: {msg}")

        def expect(name: str, shape: tuple, dtype: torch.dtype):
            # Readers return exactly the documented dtypes; pairs built in code may use another
            # floating-point precision (float64 for gradient checks), never integers.
            t = getattr(self, name)
            kind_ok = t.dtype == dtype or (dtype.is_floating_point and t.dtype.is_floating_point)
            if tuple(t.shape) != shape or not kind_ok:
                fail(f"{name} is {t.dtype} of shape {tuple(t.shape)}, expected {dtype} {shape}")

        for name in ("image1", "image2"):
            expect(name, (3, h, w), torch.float32)
            t = getattr(self, name)
            lo, hi = _extremes(t)         # one pass; NaN propagates and fails both tests
            if not (lo >= 0 and hi <= 1):
                fail(f"{name} has values outside [0, 1]")
        for name in ("depth1", "depth2"):
            t = getattr(self, name)
            src = self.sources.get(name, where)
            if tuple(t.shape) != (1, h, w):
                raise DatasetError(
                    f"{src}: depth is {t.shape[-1]}x{t.shape[-2]} but the image is {w}x{h}"
                )
            expect(name, (1, h, w), torch.float32)
            lo, hi = _extremes(t)
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise DatasetError(f"{src}: depth has non-finite values")
            if not lo > 0:
                raise DatasetError(f"{src}: depth has zero or negative values")
        expect("intrinsics", (3, 3), torch.float64)
        for name in ("cam2_from_cam1", "cam1_from_world", "cam2_from_world"):
            if getattr(self, name) is not None:
                expect(name, (4, 4), torch.float64)
        if self.flow is not None:
            if tuple(self.flow.shape) != (2, h, w):
                src = self.sources.get("flow", where)
                raise DatasetError(f"{src}: flow is {self.flow.shape[-1]}x{self.flow.shape[-2]} "
                                   f"but the image is {w}x{h}")
            expect("flow", (2, h, w), torch.float32)
        if self.flow_valid is not None:
            expect("flow_valid", (1, h, w), torch.bool)
        for name in ("depth_provenance1", "depth_provenance2"):
            if getattr(self, name) is not None:
                expect(name, (1, h, w), torch.uint8)
                if int(getattr(self, name).max()) > UNKNOWN:
                    fail(f"{name} has codes above {UNKNOWN} ({'/'.join(PROVENANCE_NAMES)})")
        return self

    def to(self, device: torch.device | str) -> "FramePair":
        """A copy with every tensor on ``device`` (dtypes unchanged)."""
        moved = {}
        for name in _TENSOR_FIELDS:
            t = getattr(self, name)
            moved[name] = None if t is None else t.to(device)
        return replace(self, **moved)


_TENSOR_FIELDS = ("image1", "image2", "depth1", "depth2", "intrinsics", "cam2_from_cam1",
                  "cam1_from_world", "cam2_from_world", "flow", "flow_valid",
                  "depth_provenance1", "depth_provenance2")


@dataclass
class FramePairBatch:
    """``B`` frame pairs of the same size stacked along a leading batch dimension.

    Shape: as :class:`FramePair` with a leading ``B``; optional fields are ``None`` unless every
    pair has them, except the depth provenance maps, which are stacked (all :data:`MEASURED` for
    a pair without one) as soon as one pair has them.
    """

    ids: list
    image1: torch.Tensor
    image2: torch.Tensor
    depth1: torch.Tensor
    depth2: torch.Tensor
    intrinsics: torch.Tensor
    cam2_from_cam1: torch.Tensor
    cam1_from_world: Optional[torch.Tensor] = None
    cam2_from_world: Optional[torch.Tensor] = None
    flow: Optional[torch.Tensor] = None
    flow_valid: Optional[torch.Tensor] = None
    depth_provenance1: Optional[torch.Tensor] = None
    depth_provenance2: Optional[torch.Tensor] = None

    @classmethod
    def stack(cls, pairs: list[FramePair]) -> "FramePairBatch":
        if not pairs:
            raise ValueError("cannot stack an empty list of frame pairs")
        sizes = {p.size for p in pairs}
        if len(sizes) != 1:
            raise ShapeError(f"frame pairs of different sizes cannot form one batch: {sorted(sizes)}")

        def opt(name):
            vals = [getattr(p, name) for p in pairs]
            return None if any(v is None for v in vals) else torch.stack(vals)

        def provenance(name):
            # None means "all measured", so a pair without a map stacks as all MEASURED.
            vals = [getattr(p, name) for p in pairs]
            if all(v is None for v in vals):
                return None
            return torch.stack([torch.full_like(p.depth1, MEASURED, dtype=torch.uint8)
                                if v is None else v for p, v in zip(pairs, vals)])

        return cls(
            ids=[p.id for p in pairs],
            image1=torch.stack([p.image1 for p in pairs]),
            image2=torch.stack([p.image2 for p in pairs]),
            depth1=torch.stack([p.depth1 for p in pairs]),
            depth2=torch.stack([p.depth2 for p in pairs]),
            intrinsics=torch.stack([p.intrinsics for p in pairs]),
            cam2_from_cam1=torch.stack([p.cam2_from_cam1 for p in pairs]),
            cam1_from_world=opt("cam1_from_world"),
            cam2_from_world=opt("cam2_from_world"),
            flow=opt("flow"),
            flow_valid=opt("flow_valid"),
            depth_provenance1=provenance("depth_provenance1"),
            depth_provenance2=provenance("depth_provenance2"),
        )
