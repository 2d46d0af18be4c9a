"""Dense maps from sparse measurements, guided by the image (for KITTI's sparse disparity).

Method: normalised convolution with a joint bilateral kernel. Every unmeasured pixel takes the
average of the measurements around it, each weighted by its distance in the image *and* by how
similar its colour is to the pixel's own (the guide image), so a gap on a car is filled from the
car, not from the road behind it; plain nearest-neighbour filling copies whichever measurement is
closest, across an edge or not. A second pass closes what the first left open. Larger holes are
filled coarse to fine: the known values and the guide are halved in size, filled there the same
way (recursively), and brought back up for the pixels still missing.

Fill in disparity (inverse depth), not depth: on a plane, disparity is an affine function of the
pixel position, so averaging neighbours on both sides is exact there.

Pixels farther than ``max_gap_px`` from any measurement (the image region above a laser
scanner's field of view, large holes) and the ``exclude``d ones (the sky) are left unfilled;
:func:`~weathergen.datasets.depth.complete_depth` completes the former and gives the sky its
far depth.
"""

from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

#: Window radius (pixels) and spatial sigma of the bilateral kernel at every pyramid level.
_RADIUS = 3
_SIGMA_SPACE = 1.5


def fill_sparse(values: np.ndarray, measured: np.ndarray, guide: np.ndarray, *,
                max_gap_px: float = 24.0, color_sigma: float = 0.05,
                exclude: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """Fill the unmeasured pixels of a sparse map from nearby measurements, respecting edges.

    Shape: values (H, W) float (ignored where not measured); measured (H, W) bool; guide (H, W, 3)
    RGB float in [0, 1]. Returns ``(filled (H, W) float32, known (H, W) bool)``: measured pixels
    keep their value exactly; ``known`` is False (and ``filled`` NaN) where no measurement lies
    within ``max_gap_px`` pixels, and at ``exclude`` (an (H, W) bool mask, or None).
    ``color_sigma`` is the colour tolerance of the kernel, in the guide's [0, 1] units.
    """
    values = np.asarray(values, np.float32)
    measured = np.asarray(measured, bool)
    if values.shape != measured.shape or values.ndim != 2:
        raise ValueError(f"values and mask must be (H, W) alike, got {values.shape} and {measured.shape}")
    if guide.shape[:2] != values.shape:
        raise ValueError(f"guide is {guide.shape[:2]}, values are {values.shape}")
    if not measured.any():
        return np.full(values.shape, np.nan, np.float32), np.zeros_like(measured)
    # distance of every pixel to the nearest measurement (measured pixels are the zeros)
    gap = cv2.distanceTransform((~measured).astype(np.uint8), cv2.DIST_L2, 5)
    wanted = gap <= max_gap_px
    if exclude is not None:
        wanted &= ~np.asarray(exclude, bool)
    filled, known = _fill_pyramid(np.where(measured, values, 0).astype(np.float32), measured,
                                  np.ascontiguousarray(guide, np.float32), wanted, color_sigma)
    known &= wanted
    filled[~known] = np.nan
    filled[measured] = values[measured]
    return filled, known | measured


def _bilateral_pass(values, known, guide, color_sigma, wanted):
    """One normalised joint-bilateral pass: (values, known) -> (values, known), more pixels known
    (``wanted`` ones only). The weighted sum and the weight are filtered together (one
    three-channel filter), on the rows that hold wanted pixels (and the kernel's reach)."""
    rows = np.flatnonzero((wanted & ~known).any(axis=1))
    lo, hi = max(rows[0] - _RADIUS, 0), rows[-1] + _RADIUS + 1
    part = slice(lo, hi)
    stack = np.dstack([np.where(known[part], values[part], 0), known[part],
                       np.zeros_like(values[part])]).astype(np.float32)
    num, den, _ = cv2.split(cv2.ximgproc.jointBilateralFilter(
        np.ascontiguousarray(guide[part]), stack, 2 * _RADIUS + 1, color_sigma, _SIGMA_SPACE))
    new = np.zeros_like(known)
    new[part] = wanted[part] & ~known[part] & (den > 1e-4)
    out = values.copy()
    out[new] = num[new[part]] / den[new[part]]
    return out, known | new


def _fill_pyramid(values, known, guide, wanted, color_sigma):
    for _ in range(2):
        if not (wanted & ~known).any():
            return values, known
        values, known = _bilateral_pass(values, known, guide, color_sigma, wanted)
    missing = wanted & ~known
    h, w = known.shape
    if not missing.any() or min(h, w) < 2 * (2 * _RADIUS + 1):
        return values, known
    # coarse level: block averages of the known values, the guide halved
    size = ((w + 1) // 2, (h + 1) // 2)
    weight = cv2.resize(known.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    total = cv2.resize(np.where(known, values, 0).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    coarse_known = weight > 0
    coarse_vals = np.where(coarse_known, total / np.maximum(weight, 1e-12), 0).astype(np.float32)
    coarse_guide = cv2.resize(guide, size, interpolation=cv2.INTER_AREA)
    coarse_wanted = cv2.resize(wanted.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    coarse_vals, coarse_known = _fill_pyramid(coarse_vals, coarse_known, coarse_guide, coarse_wanted,
                                              color_sigma)
    up_vals, up_known = _joint_upsample(coarse_vals, coarse_known, coarse_guide, guide, missing,
                                        color_sigma)
    take = missing & up_known
    values = values.copy()
    values[take] = up_vals[take]
    return values, known | take


def _joint_upsample(values, known, guide, fine_guide, where, color_sigma):
    """A coarse fill brought up to the fine level at the pixels ``where`` (joint bilateral
    upsampling, Kopf et al. 2007): each takes the known coarse pixels of its 3 x 3 coarse
    neighbourhood, weighted by distance and by how alike their colour is to its own, so a pixel
    above a car takes the trees' value, not the car's; with no alike neighbour, the nearest one.

    Shape: values, known (h, w); guide (h, w, 3); fine_guide (H, W, 3); where (H, W) ->
    ``(values (H, W) float32, known (H, W) bool)``, set at ``where`` only.
    """
    h, w = known.shape
    ys, xs = np.nonzero(where)
    cy, cx = (ys + 0.5) / 2 - 0.5, (xs + 0.5) / 2 - 0.5
    colour = fine_guide[ys, xs]
    num = np.zeros(len(ys), np.float64)
    den = np.zeros(len(ys), np.float64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            qy = np.clip(np.rint(cy).astype(np.int64) + dy, 0, h - 1)
            qx = np.clip(np.rint(cx).astype(np.int64) + dx, 0, w - 1)
            far = ((qy - cy) ** 2 + (qx - cx) ** 2) / (2 * _SIGMA_SPACE ** 2)
            unlike = ((guide[qy, qx] - colour) ** 2).sum(axis=1) / (2 * color_sigma ** 2)
            weight = known[qy, qx] * np.exp(-far - unlike)
            num += weight * values[qy, qx]
            den += weight
    qy = np.clip(np.rint(cy).astype(np.int64), 0, h - 1)
    qx = np.clip(np.rint(cx).astype(np.int64), 0, w - 1)
    nearest = known[qy, qx]
    ok = den > 1e-12
    out = np.zeros(where.shape, np.float32)
    got = np.zeros(where.shape, bool)
    out[ys, xs] = np.where(ok, num / np.maximum(den, 1e-300), values[qy, qx])
    got[ys, xs] = ok | nearest
    return out, got
