"""Do a dataset's depth and cameras agree with its own ground-truth flow?

Weather is placed in 3D from depth and cameras; the flow of the static scene follows from them
(:func:`~weathergen.geometry.reprojection_flow`). Where a dataset also has ground-truth flow, the
two must agree on pixels that are static and visible in both frames. A wrong convention (an
inverted extrinsic, a depth scale applied to depth but not to the cameras, a flipped axis, range
instead of camera-z depth) shows up at once as a large disagreement, before any weather is
rendered.

Pixels compared: ground-truth flow valid, frame-1 depth measured (not filled in by the reader),
not on a moving object where the reader knows them (KITTI's object map), landing inside frame 2 in
front of camera 2, and visible there: the camera-2 depth of the moved point agrees with frame 2's
own depth at the landing pixel within ``visibility_tolerance`` (relative). Moving objects a
dataset does not mark (Sintel's characters) remain; they raise the upper percentiles, while the
median stays at the static scene's figure.

Without ground-truth flow (most real RGB-D recordings), the frames themselves are the witness
(:func:`photometric_errors`): frame 2, sampled where depth and cameras say each frame-1 pixel
lands, should look like frame 1 more than frame 2 at the same pixel does. A convention the wrong
way round moves the pixels the wrong way and makes frame 2 look less like frame 1 than if nothing
had moved. Lighting changes, moving things and sensor noise raise both figures alike; the check
can only judge where the cameras move the scene by a pixel or more.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..framepair import FramePair
from ..geometry import backproject, project, transform_points
from ..io.kitti_formats import read_object_map

#: Relative camera-z difference up to which a moved point counts as the surface frame 2 sees.
VISIBILITY_TOLERANCE = 0.05
#: Median predicted motion (px) below which the photometric check cannot judge the geometry.
MIN_PHOTOMETRIC_MOTION_PX = 1.0
#: Mean grey-level difference (in [0, 1]) of frames left in place above which they clearly differ
#: (about 5 of 255 levels on average: more than sensor noise and compression of a still view).
FRAMES_DIFFER = 0.02


@dataclass(frozen=True)
class GeometryStats:
    """End-point error between reprojection flow and ground-truth flow, over the compared pixels.

    ``median_px``, ``p90_px`` in pixels; ``within_1px`` the fraction of pixels with an error
    below one pixel; ``pixels`` how many were compared; ``pairs`` over how many pairs.
    """

    median_px: float
    p90_px: float
    within_1px: float
    pixels: int
    pairs: int

    def summary(self) -> dict:
        return {"median_px": round(self.median_px, 4), "p90_px": round(self.p90_px, 4),
                "within_1px": round(self.within_1px, 4), "pixels": self.pixels, "pairs": self.pairs}


def static_mask(pair: FramePair) -> Optional[np.ndarray]:
    """Pixels the reader knows to be static (KITTI's object map), or None when it does not know."""
    path = pair.sources.get("objects")
    if path is None:
        return None
    return read_object_map(path) == 0


def flow_errors(pair: FramePair, *, visibility_tolerance: float = VISIBILITY_TOLERANCE,
                static: Optional[np.ndarray] = None) -> Optional[np.ndarray]:
    """Per-pixel error (px) of the reprojection flow against the pair's ground truth, on the
    compared pixels (see the module text). Shape: returns (M,) float64, or None without flow.
    ``static`` (H, W) bool restricts the comparison further.
    """
    if pair.flow is None:
        return None
    h, w = pair.size
    k = pair.intrinsics.double()
    pts1 = backproject(pair.depth1.double(), k).flatten(1).T                # (HW, 3)
    pts2 = transform_points(pair.cam2_from_cam1.double(), pts1)
    pix2, z2 = project(pts2, k)
    grid = torch.stack(torch.meshgrid(torch.arange(h, dtype=torch.float64),
                                      torch.arange(w, dtype=torch.float64), indexing="ij")[::-1])
    predicted = pix2.T.reshape(2, h, w) - grid
    keep = torch.ones(h, w, dtype=torch.bool)
    if pair.flow_valid is not None:
        keep &= pair.flow_valid[0]
    if pair.depth_measured1 is not None:
        keep &= pair.depth_measured1[0]
    if static is not None:
        keep &= torch.from_numpy(np.asarray(static, bool))
    # where the ground truth lands, frame 2 must see the moved point (not something in front of it)
    target = grid + pair.flow.double()
    tx, ty = target[0].round().long(), target[1].round().long()
    inside = (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h) & (z2.reshape(h, w) > 0)
    keep &= inside
    seen = pair.depth2[0].double()[ty.clamp(0, h - 1), tx.clamp(0, w - 1)]
    keep &= (z2.reshape(h, w) - seen).abs() <= visibility_tolerance * seen
    if pair.depth_measured2 is not None:
        keep &= pair.depth_measured2[0][ty.clamp(0, h - 1), tx.clamp(0, w - 1)]
    err = torch.linalg.vector_norm(predicted - pair.flow.double(), dim=0)
    return err[keep].numpy()


def photometric_errors(pair: FramePair, *, visibility_tolerance: float = VISIBILITY_TOLERANCE
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The frames as witness of depth and cameras, for pairs without ground-truth flow.

    For every frame-1 pixel with measured depth that lands inside frame 2, in front of camera 2
    and visible there (as in :func:`flow_errors`, with frame 2's depth at the landing pixel):
    the absolute grey-level difference between frame 1 and frame 2 sampled (bilinearly) at the
    landing point, the same difference with frame 2 at the same pixel (no motion), and the length
    of the predicted motion. Grey levels are the mean of the channels, in [0, 1].
    Shape: returns three (M,) float64 arrays.
    """
    h, w = pair.size
    k = pair.intrinsics.double().cpu()
    pts1 = backproject(pair.depth1.double().cpu(), k).flatten(1).T            # (HW, 3)
    pix2, z2 = project(transform_points(pair.cam2_from_cam1.double().cpu(), pts1), k)
    x2, y2, z2 = pix2[:, 0].reshape(h, w), pix2[:, 1].reshape(h, w), z2.reshape(h, w)
    grid = torch.stack(torch.meshgrid(torch.arange(h, dtype=torch.float64),
                                      torch.arange(w, dtype=torch.float64), indexing="ij")[::-1])
    # inside frame 2: within the pixels' extent (centres at 0 .. w - 1)
    keep = (x2 >= -0.5) & (x2 <= w - 0.5) & (y2 >= -0.5) & (y2 <= h - 0.5) & (z2 > 0)
    if pair.depth_measured1 is not None:
        keep &= pair.depth_measured1[0].cpu()
    tx, ty = x2.round().long().clamp(0, w - 1), y2.round().long().clamp(0, h - 1)
    seen = pair.depth2[0].double().cpu()[ty, tx]
    keep &= (z2 - seen).abs() <= visibility_tolerance * seen
    if pair.depth_measured2 is not None:
        keep &= pair.depth_measured2[0].cpu()[ty, tx]
    grey1 = pair.image1.double().cpu().mean(0)
    grey2 = pair.image2.double().cpu().mean(0)
    where = torch.stack([x2 / max(w - 1, 1) * 2 - 1, y2 / max(h - 1, 1) * 2 - 1], dim=-1)[None]
    warped = F.grid_sample(grey2[None, None], where, mode="bilinear", padding_mode="border",
                           align_corners=True)[0, 0]
    motion = torch.linalg.vector_norm(torch.stack([x2, y2]) - grid, dim=0)
    return ((warped - grey1).abs()[keep].numpy(), (grey2 - grey1).abs()[keep].numpy(),
            motion[keep].numpy())


@dataclass(frozen=True)
class PhotometricStats:
    """Pooled :func:`photometric_errors` of a scene's pairs.

    ``error``: mean grey-level difference between frame 1 and frame 2 moved by depth and cameras;
    ``unmoved_error``: the same with nothing moved; ``motion_px``: median predicted motion;
    ``coverage``: share of frame-1 pixels compared; ``pixels``, ``pairs``: how many compared.
    """

    error: float
    unmoved_error: float
    motion_px: float
    coverage: float
    pixels: int
    pairs: int

    @property
    def judged(self) -> bool:
        """Whether the cameras move the scene enough for the frames to tell."""
        return self.pixels > 0 and self.motion_px >= MIN_PHOTOMETRIC_MOTION_PX

    @property
    def explained(self) -> bool:
        """Whether depth and cameras explain frame 2 better than no motion at all does."""
        return self.error < self.unmoved_error

    @property
    def still_cameras_moving_frames(self) -> bool:
        """Whether the cameras predict (almost) no motion while the frames clearly differ: poses
        that do not follow the camera (the same pose for every frame, say)."""
        return self.pixels > 0 and not self.judged and self.unmoved_error >= FRAMES_DIFFER

    def summary(self) -> dict:
        return {"error": round(self.error, 5), "unmoved_error": round(self.unmoved_error, 5),
                "motion_px": round(self.motion_px, 3), "coverage": round(self.coverage, 4),
                "pixels": self.pixels, "pairs": self.pairs}


def summarize_photometric(results: Sequence[tuple], total_pixels: int) -> Optional[PhotometricStats]:
    """Pool :func:`photometric_errors` results; ``total_pixels``: frame-1 pixels of those pairs."""
    if not results:
        return None
    warped, unmoved, motion = (np.concatenate([r[i] for r in results]) for i in range(3))
    if warped.size == 0:
        return PhotometricStats(float("nan"), float("nan"), float("nan"), 0.0, 0, len(results))
    return PhotometricStats(error=float(warped.mean()), unmoved_error=float(unmoved.mean()),
                            motion_px=float(np.median(motion)),
                            coverage=float(warped.size / max(total_pixels, 1)),
                            pixels=int(warped.size), pairs=len(results))


def summarize(errors: Sequence[np.ndarray]) -> Optional[GeometryStats]:
    """Pool the per-pixel errors of several pairs. None when no pixel was compared."""
    pooled = [e for e in errors if e is not None]
    if not pooled:
        return None
    allerr = np.concatenate(pooled)
    if allerr.size == 0:
        return GeometryStats(float("nan"), float("nan"), float("nan"), 0, len(pooled))
    return GeometryStats(median_px=float(np.median(allerr)), p90_px=float(np.quantile(allerr, 0.9)),
                         within_1px=float((allerr < 1.0).mean()), pixels=int(allerr.size),
                         pairs=len(pooled))


def sample_indices(count: int, at_most: int) -> list[int]:
    """Up to ``at_most`` indices spread evenly over ``range(count)``, first and last included."""
    if count <= at_most:
        return list(range(count))
    if at_most == 1:
        return [0]
    return sorted({round(i * (count - 1) / (at_most - 1)) for i in range(at_most)})
