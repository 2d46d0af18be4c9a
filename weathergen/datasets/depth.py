"""Depth you can trust: where each pixel's depth comes from, the sky decided, the rest completed.

A pixel without a measurement is not the sky. A reader hands its measured depth to
:func:`complete_depth`, which sorts every pixel into one provenance class
(:data:`~weathergen.framepair.MEASURED`, ``COMPLETED``, ``SKY``, ``UNKNOWN``) and gives each its
depth:

1. **Sky** is a user's mask where one is given, else :func:`estimate_sky`: pixels without a
   measurement, above the highest measurement of their column, smooth (a weak image gradient),
   bright and blue to grey, connected to the top border of the frame. Only the sky gets the far
   depth (and so the full airlight of fog).
2. **Small gaps** (within ``max_gap_px`` of a measurement): the joint-bilateral fill of
   :func:`~weathergen.datasets.densify.fill_sparse`, in inverse depth, guided by the image.
3. **Large regions** (above a laser scanner's top beam, big holes): each column's top-most
   known value extends upward to the pixels above it that are not sky and not cut from it by
   sky (IP-Basic's upward extension, stopped at the sky); what that leaves (holes walled in by
   measurements) is an edge-aware membrane, each pixel the mean of its four neighbours weighted
   by how alike their colours are, solved coarse to fine; a guided filter over the completed
   pixels alone then smooths away the column streaks along the image's edges.
4. ``max_gap_px = 0`` completes nothing: unmeasured pixels that are not sky are ``UNKNOWN`` and
   get the far depth like the sky (the readers' ``--fill-gaps 0``).

Everything is NumPy and OpenCV on whole arrays (no loop over pixels). :func:`lidar_scan` makes a
LiDAR-like measurement pattern for a frame and its camera, to measure all of this against exact
depth (``scripts/depth_completion.py``; the figures are in docs/datasets.md).
"""

from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from ..framepair import COMPLETED, MEASURED, PROVENANCE_NAMES, SKY, UNKNOWN
from .densify import fill_sparse

#: The sky estimate: the largest image gradient (luminance per pixel, the largest within
#: :data:`SKY_WINDOW` pixels) and the smallest luminance a sky pixel may have, relative to the
#: frame's :data:`SKY_BRIGHT_QUANTILE` luminance quantile (the sky is among the brightest parts).
SKY_MAX_GRADIENT = 0.02
SKY_WINDOW = 5
SKY_BRIGHT_QUANTILE = 0.6
#: Once found, the sky takes the smooth blue to grey pixels at least this share of its median
#: luminance (a lens darkens the frame's corners).
SKY_RELATIVE_BRIGHTNESS = 0.6
#: Blue to grey: a sky pixel's blue is at least its red and its green less this.
SKY_HUE = 0.02
#: The largest distance (RGB) between the mean colours of two parts of one sky.
SKY_COLOR_SPREAD = 0.25
#: The colour tolerance of the vote that settles the pixels along the sky's edge.
SKY_EDGE_COLOR_SIGMA = 0.05
#: A measurement is stray when it is nearer (or farther) than all its measured neighbours within
#: a STRAY_WINDOW square (at least STRAY_NEIGHBOURS) by more than STRAY_AGREE of the inverse depth.
STRAY_WINDOW = 9
STRAY_NEIGHBOURS = 2
STRAY_AGREE = 0.1
#: The membrane fill of large holes: Jacobi sweeps at each level, colour tolerance of its links.
MEMBRANE_SWEEPS = 20
MEMBRANE_COLOR_SIGMA = 0.1
#: The guided-filter smoothing of large completed regions: radius (pixels), regularisation.
SMOOTH_RADIUS = 4
SMOOTH_EPS = 1e-3


def complete_depth(depth: np.ndarray, measured: np.ndarray, image: np.ndarray, *,
                   far_depth: float, max_gap_px: float = 24.0, sky: Optional[np.ndarray] = None,
                   estimate: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A dense depth map and its provenance from measured depth.

    Shape: depth (H, W) float (read where ``measured`` only); measured (H, W) bool; image
    (H, W, 3) RGB in [0, 1]; sky (H, W) bool or None (then :func:`estimate_sky` decides, unless
    ``estimate`` is False: no sky). Returns ``(depth (H, W) float32, provenance (H, W) uint8)``:
    measured pixels keep their depth exactly, the sky and unknown pixels get ``far_depth``.
    """
    measured = np.asarray(measured, bool)
    if sky is None:
        sky = estimate_sky(image, measured) if estimate else np.zeros_like(measured)
    sky = np.asarray(sky, bool) & ~measured
    inverse = np.where(measured, 1.0 / np.where(measured, depth, 1.0), 0.0).astype(np.float32)
    prov = np.where(measured, MEASURED, np.where(sky, SKY, UNKNOWN)).astype(np.uint8)
    out = np.where(measured, depth, far_depth).astype(np.float32)
    if max_gap_px <= 0 or not measured.any() or (prov != UNKNOWN).all():
        return out, prov
    seeds = measured & ~stray_measurements(inverse, measured)
    values, known = fill_sparse(inverse, seeds, image, max_gap_px=max_gap_px, exclude=sky)
    values = np.where(measured, inverse, values)
    known = (known | measured) & ~sky
    large = ~known & ~sky
    if large.any():
        values, known = _complete_large(values, known, large, sky, image)
    done = known & ~measured & np.isfinite(values) & (values > 0)
    out[done] = 1.0 / values[done]
    prov[done] = COMPLETED
    return out, prov


def stray_measurements(inverse: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Measurements nearer or farther than every measured neighbour within :data:`STRAY_WINDOW`
    // 2 pixels (at least :data:`STRAY_NEIGHBOURS` of them) by more than :data:`STRAY_AGREE` of
    the inverse depth: a laser return projected from elsewhere. They keep their pixel but seed no
    fill. Shape: (H, W) each -> (H, W) bool."""
    ring = np.ones((STRAY_WINDOW, STRAY_WINDOW), np.uint8)
    ring[STRAY_WINDOW // 2, STRAY_WINDOW // 2] = 0
    inverse = inverse.astype(np.float32)
    nearest = cv2.dilate(np.where(measured, inverse, 0).astype(np.float32), ring)
    farthest = cv2.erode(np.where(measured, inverse, np.inf).astype(np.float32), ring)
    count = cv2.filter2D(measured.astype(np.float32), -1, ring.astype(np.float32),
                         borderType=cv2.BORDER_CONSTANT)
    odd = (inverse > (1 + STRAY_AGREE) * nearest) | (inverse < (1 - STRAY_AGREE) * farthest)
    return measured & odd & (count >= STRAY_NEIGHBOURS - 0.5)


def _complete_large(values, known, large, sky, image):
    """Large regions: upward extension in each column (not through the sky), the edge-aware
    membrane for the rest, then an edge-aware smoothing of what was completed here.
    Shape: (H, W) each."""
    values = np.where(known, values, 0).astype(np.float32)
    up = extend_upward(values, known, sky)
    values, known = np.where(up, _column_tops(values, known), values), known | up
    rest = large & ~known
    if rest.any():
        guide = np.ascontiguousarray(image, np.float32)
        values = np.where(rest, _membrane(values, known, guide, ~sky), values)
        known = known | rest
    return _smooth_within(values, known & large, known, image), known


def _column_tops(values, known):
    """Every pixel takes the top-most known value of its column. Shape: (H, W) -> (H, W)."""
    top = np.argmax(known, axis=0)
    return np.broadcast_to(values[top, np.arange(values.shape[1])], values.shape)


def _membrane(values, known, guide, open_):
    """The unknown pixels filled so that each is the weighted mean of its four neighbours, the
    weights falling with the colour difference (:data:`MEMBRANE_COLOR_SIGMA`) and zero towards
    pixels that are not ``open_`` (the sky): an edge-aware harmonic fill, exact on a plane's
    inverse depth within a surface of one colour. Solved coarse to fine: the half-size problem's
    answer, brought up bilinearly, starts :data:`MEMBRANE_SWEEPS` Jacobi sweeps.

    Shape: values, known, open_ (H, W); guide (H, W, 3) -> (H, W) float32.
    """
    h, w = known.shape
    if min(h, w) >= 8:
        size = ((w + 1) // 2, (h + 1) // 2)
        weight = cv2.resize(known.astype(np.float32), size, interpolation=cv2.INTER_AREA)
        total = cv2.resize(np.where(known, values, 0).astype(np.float32), size,
                           interpolation=cv2.INTER_AREA)
        coarse = _membrane(np.where(weight > 0, total / np.maximum(weight, 1e-12), 0), weight > 0,
                           cv2.resize(guide, size, interpolation=cv2.INTER_AREA),
                           np.ones(size[::-1], bool))
        start = cv2.resize(coarse.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
    else:
        start = np.full((h, w), values[known].mean() if known.any() else 0, np.float32)
    v = np.where(known, values, start).astype(np.float32)
    pads = [(1, 0), (0, 1)]
    weights = []
    for axis in (0, 1):
        step = np.diff(guide, axis=axis)
        link = np.exp(-(step ** 2).sum(axis=2) / (2 * MEMBRANE_COLOR_SIGMA ** 2))
        link *= np.delete(open_, 0, axis=axis) & np.delete(open_, -1, axis=axis)
        for pad in pads:        # the link to the neighbour before and after along ``axis``
            weights.append(np.pad(link, [pad if a == axis else (0, 0) for a in (0, 1)]))
    total = np.maximum(sum(weights), 1e-12)
    for _ in range(MEMBRANE_SWEEPS):
        p = np.pad(v, 1, mode="edge")
        around = (weights[0] * p[:-2, 1:-1] + weights[1] * p[2:, 1:-1]
                  + weights[2] * p[1:-1, :-2] + weights[3] * p[1:-1, 2:])
        v = np.where(known, values, around / total)
    return v


def extend_upward(values: np.ndarray, known: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """The pixels that take their column's top-most known value: above it, not sky, and with no
    sky between them and it. Shape: (H, W) each -> (H, W) bool."""
    h = known.shape[0]
    rows = np.arange(h)[:, None]
    has = known.any(axis=0)
    top = np.where(has, np.argmax(known, axis=0), 0)
    sky_to = np.cumsum(sky, axis=0)                      # sky pixels in rows 0..r of each column
    below = sky_to[np.maximum(top - 1, 0), np.arange(known.shape[1])]
    clear = (below[None, :] - sky_to) == 0               # no sky in rows r+1 .. top-1
    return (rows < top[None, :]) & has[None, :] & ~sky & clear


def _smooth_within(values, region, known, image):
    """``values`` smoothed in ``region`` by a guided filter (He et al.) steered by ``image`` that
    averages known values alone (normalised); other pixels unchanged. Shape: (H, W) each."""
    if not region.any():
        return values
    guide = np.ascontiguousarray(image, np.float32)
    weight = known.astype(np.float32)
    num, den = (cv2.ximgproc.guidedFilter(guide, a, SMOOTH_RADIUS, SMOOTH_EPS)
                for a in ((values * weight).astype(np.float32), weight))
    ok = region & (den > 1e-3)
    out = values.copy()
    out[ok] = num[ok] / den[ok]
    return out


def estimate_sky(image: np.ndarray, measured: np.ndarray, *,
                 max_gradient: float = SKY_MAX_GRADIENT,
                 bright_quantile: float = SKY_BRIGHT_QUANTILE) -> np.ndarray:
    """The sky of a frame that does not label it: pixels without a measurement, above the highest
    measurement of their column (every row of a column without one), smooth, bright, blue to grey
    (blue at least red and green), connected to the top border.

    Of several such parts, those whose mean colour is far from the largest one's are not sky.
    Smooth is judged twice: a core whose luminance gradient stays below ``max_gradient`` within
    :data:`SKY_WINDOW` pixels (away from every edge), then grown to the pixels whose own gradient
    stays below twice that (up to the edges of what stands against the sky). Bright is at least
    the frame's ``bright_quantile`` luminance quantile.

    Shape: image (H, W, 3) RGB in [0, 1], measured (H, W) bool -> (H, W) bool.
    """
    image = np.ascontiguousarray(image, np.float32)
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    blurred = cv2.GaussianBlur(grey, (0, 0), 1.0)
    gradient = np.hypot(cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3),
                        cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    h = measured.shape[0]
    top = np.where(measured.any(axis=0), np.argmax(measured, axis=0), h)
    above = np.arange(h)[:, None] < top[None, :]
    possible = above & (image[..., 2] >= image[..., :2].max(axis=2) - SKY_HUE)
    texture = cv2.dilate(gradient, np.ones((SKY_WINDOW, SKY_WINDOW), np.uint8))
    sky = _smooth_sky(possible & (grey >= np.quantile(grey, bright_quantile)), texture, gradient,
                      max_gradient, image)
    if sky.any():
        # The bright parts find the sky, which may be darker elsewhere (a lens darkens the corners)
        bright = grey >= SKY_RELATIVE_BRIGHTNESS * np.median(grey[sky])
        sky = _smooth_sky(possible & bright, texture, gradient, max_gradient, image)
        sky |= _enclosed_sky(possible & bright, texture, gradient, max_gradient, image, sky)
    return _edge_pixels(sky, above, image)


def _smooth_sky(possible, texture, gradient, max_gradient, image):
    """The smooth parts of ``possible`` that reach the top border: a core of ``texture`` below
    ``max_gradient`` grown over ``gradient`` below twice that. Shape: (H, W) each -> (H, W)."""
    core = _one_sky(_touching_top(possible & (texture <= max_gradient)), image)
    return _grown(possible & (gradient <= 2 * max_gradient), core)


def _enclosed_sky(possible, texture, gradient, max_gradient, image, sky):
    """The sky seen where it does not reach the top border (between a sign and a pole, through a
    tree): smooth parts of ``possible`` at least :data:`SKY_WINDOW` pixels wide whose hue is
    within :data:`SKY_COLOR_SPREAD` of the sky's. Shape: (H, W) each, image (H, W, 3) -> (H, W)."""
    core = (possible & (texture <= max_gradient) & ~sky).astype(np.uint8)
    wide = cv2.erode(core, np.ones((SKY_WINDOW, SKY_WINDOW), np.uint8)) > 0
    count, labels = cv2.connectedComponents(_grown(core > 0, wide).astype(np.uint8), connectivity=4)
    sizes = np.maximum(np.bincount(labels.ravel(), minlength=count), 1)
    means = np.stack([np.bincount(labels.ravel(), image[..., c].ravel(), count) for c in range(3)],
                     1) / sizes[:, None]
    ref = image[sky].mean(axis=0)
    hue = means / np.maximum(means.mean(axis=1, keepdims=True), 1e-6)
    keep = np.linalg.norm(hue - ref / max(ref.mean(), 1e-6), axis=1) <= SKY_COLOR_SPREAD
    keep[0] = False
    return _grown(possible & (gradient <= 2 * max_gradient), keep[labels])


def _edge_pixels(sky: np.ndarray, above: np.ndarray, image: np.ndarray) -> np.ndarray:
    """``sky`` with the pixels along its edge (within :data:`SKY_WINDOW` // 2 pixels, ``above``
    the measurements) that look more like the sky around them than like what is not sky: a vote
    of the decided pixels around, weighted by colour (a joint bilateral filter)."""
    band = cv2.dilate(sky.astype(np.uint8), np.ones((SKY_WINDOW, SKY_WINDOW), np.uint8)) > 0
    band &= ~sky & above
    if not band.any():
        return sky
    rows = np.flatnonzero(band.any(axis=1))
    part = slice(max(rows[0] - SKY_WINDOW, 0), rows[-1] + SKY_WINDOW + 1)   # the kernel's reach
    decided = (~band[part]).astype(np.float32)
    votes = cv2.ximgproc.jointBilateralFilter(
        np.ascontiguousarray(image[part]), np.dstack([decided * sky[part], decided, decided * 0]),
        SKY_WINDOW + 2, SKY_EDGE_COLOR_SIGMA, SKY_WINDOW / 2)
    out = sky.copy()
    out[part] |= band[part] & (votes[..., 0] > 0.5 * votes[..., 1])
    return out


def _one_sky(mask: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The parts of ``mask`` whose mean colour is within :data:`SKY_COLOR_SPREAD` of its largest
    part's (a frame has one sky: a smooth grey wall beside a blue sky is not part of it)."""
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=4)
    if count <= 2:
        return mask
    sizes = np.bincount(labels.ravel(), minlength=count).astype(np.float64)
    means = np.stack([np.bincount(labels.ravel(), image[..., c].ravel(), count)
                      for c in range(3)], 1) / np.maximum(sizes, 1)[:, None]
    sizes[0] = 0
    means /= np.maximum(means.mean(axis=1, keepdims=True), 1e-6)      # hue, not brightness
    keep = np.linalg.norm(means - means[np.argmax(sizes)], axis=1) <= SKY_COLOR_SPREAD
    keep[0] = False
    return keep[labels]


def _grown(mask: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """The connected parts (4-neighbours) of ``mask`` that hold a seed. (H, W) -> (H, W)."""
    count, labels = cv2.connectedComponents((mask | seeds).astype(np.uint8), connectivity=4)
    keep = np.zeros(count, bool)
    keep[labels[seeds]] = True
    keep[0] = False
    return keep[labels]


def _touching_top(mask: np.ndarray) -> np.ndarray:
    """The connected parts (4-neighbours) of ``mask`` that reach the top row. (H, W) -> (H, W)."""
    seeds = np.zeros_like(mask)
    seeds[0] = mask[0]
    return _grown(mask, seeds)


def provenance_shares(provenance) -> dict:
    """The share of each provenance class among a map's pixels, rounded to 1e-4 (names as in
    :data:`~weathergen.framepair.PROVENANCE_NAMES`). ``None`` (all measured) gives measured 1."""
    if provenance is None:
        return {name: float(i == MEASURED) for i, name in enumerate(PROVENANCE_NAMES)}
    counts = np.bincount(np.asarray(provenance).ravel(), minlength=len(PROVENANCE_NAMES))
    total = max(int(counts.sum()), 1)
    return {name: round(float(c) / total, 4) for name, c in zip(PROVENANCE_NAMES, counts)}


def lidar_scan(shape: tuple[int, int], intrinsics: np.ndarray, *, beams: int = 64,
               top_deg: float = 2.0, bottom_deg: float = -24.9, step_px: float = 4.0,
               dropout: float = 0.1, seed: int = 0) -> np.ndarray:
    """A LiDAR-like measurement pattern (a Velodyne HDL-64E's, level with the camera): ``beams``
    horizontal lines at elevations evenly spread from ``top_deg`` to ``bottom_deg``, each sampled
    every ``step_px`` pixels from a random phase, ``dropout`` of the samples lost (dark or
    specular surfaces); nothing above the top beam. Remove the sky from it before use (the sky
    returns nothing).

    Shape: shape (H, W), intrinsics (3, 3) -> (H, W) bool, True where a sample lands.
    """
    h, w = shape
    rng = np.random.default_rng(seed)
    fy, cy = float(intrinsics[1, 1]), float(intrinsics[1, 2])
    elevations = np.deg2rad(np.linspace(top_deg, bottom_deg, beams))
    rows = np.rint(cy - fy * np.tan(elevations)).astype(np.int64)
    out = np.zeros((h, w), bool)
    for row in np.unique(rows[(rows >= 0) & (rows < h)]):
        cols = np.rint(np.arange(rng.uniform(0, step_px), w, step_px)).astype(np.int64)
        cols = cols[(cols < w) & (rng.random(len(cols)) >= dropout)]
        out[row, cols] = True
    return out
