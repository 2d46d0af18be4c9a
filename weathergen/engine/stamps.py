"""Stage 2 of the render core: looks -> stamps (no gradient).

Each stamp entry's template (:class:`~weathergen.engine.tracks.Looks`) is rotated and scaled to
its own footprint on a pixel-centred grid, sampled from a mip level no finer than twice the
footprint (no aliasing for far, tiny particles), zero outside the footprint's disc. Small stamps
without a defocus blur are *phase stamps* (:data:`PHASE_SIDE`): sampled every 1 / P pixel
(P = 4 up to 5 pixels wide, 2 up to 9), each value the template averaged over the pixel square
centred there, so that the splat can place them at a particle's exact sub-pixel position; the
others are sampled once per pixel (small blurred ones box-filtered: 4 x 4 or 2 x 2 samples); then
disc-blurred by the defocus radius (a normalised disc, the stamp growing by 2 r) and brightened
where asked (:func:`defocus_brighten`); a brightened stamp is then softened by a normalised box
of :func:`soft_box` applied twice (a tent per axis: it keeps the rule's light and turns the rim
the brightening lifts into a ramp; the stamp grows by ``b − 1`` on each side). Stamps at least
:data:`COARSE_SIDE` pixels wide (fog, large dust) are drawn for a grid ``2**L`` times coarser than the image (see
:func:`stamp_geometry`). A stamp's looks are this file's alone: how a template is sampled, the
disc that cuts it, the defocus kernel.

Layout (:class:`StampSet`): every stamp with a one-pixel zero border, row-major, one after the
other in one flat tensor; ragged, so a call costs a bounded number of tensor operations:

- samples: every stamp pixel's ``sub x sub`` sample positions are computed for all entries of a
  supersampling factor at once and read with one ``grid_sample`` from an atlas holding every mip
  level of every template (one-pixel zero borders between them, so a read never bleeds into a
  neighbour);
- disc blur: the disc is a stack of rows of half-width ``w(dy)``; a blurred pixel sums, over the
  disc's rows, box sums of the stamp's rows, each the difference of two prefix sums. Prefix sums
  are taken per stamp row (never across stamps, so a stamp does not depend on the others), in
  float64 (where a row is all zeros the difference is exactly zero: blurred stamps stay exactly
  zero outside their support);
- phase stamps: per stamp side, one dense batch of samples at every 1 / P pixel, averaged over
  P x P windows (separable pairwise sums) and copied whole to the stamps' places;
- softening: stamps grouped by similar sides (work proportional to their pixels, not to the
  count times the largest), four box passes per group, each along one axis of every stamp at
  once (differences of per-row or per-column prefix sums in float64, as the disc blur).

Elementwise operations are those whose result does not depend on an element's position in its
tensor (``exp``/``log`` rather than ``pow`` and ``sigmoid``, whose vectorised and scalar CPU
kernels round differently), so a stamp is the same whatever other stamps the call holds.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..errors import ConfigError
from .ragged import runs, starts
from .templates import TemplateLibrary
from .tracks import Looks

# Stamps at least this many pixels wide (fog, large dust) are splatted on a coarser grid (the
# largest power-of-two factor up to 2**COARSE_MAX_LEVEL = 8 that keeps them >= COARSE_MIN_SIDE
# coarse pixels wide: 8 for every stamp of 128 px or more) and upsampled; see docs/engine.md for
# the accuracy. None (the ``coarse_side`` argument) renders everything exactly.
COARSE_SIDE = 128
COARSE_MIN_SIDE = 16
COARSE_MAX_LEVEL = 3
#: Tolerance of the disc test (relative squared radius): rim samples of even-sized footprints
#: lie exactly on the circle, and the margin keeps them inside whatever the last bit of rounding.
RIM_MARGIN = 1e-5
#: Stamp samples (or blur elements) handled per chunk.
STAMP_CHUNK_ELEMENTS = 1 << 16
#: Stamps up to this side (without a defocus blur) are *phase stamps*: sampled on a grid P times
#: finer than the pixels (P = 4 up to 5 pixels, 2 up to 9), so that the splat places them at
#: the particle's sub-pixel position to within 1 / P pixel instead of shifting a pixel-centred
#: stamp by a one-pixel bilinear tent (which widened far particles by up to half their size).
PHASE_SIDE = 9
#: P per phase-stamp side (see :func:`stamp_geometry`).
PHASE_FACTORS = {s: 4 if s <= 5 else 2 for s in range(3, PHASE_SIDE + 1, 2)}


def _allowed_sides(limit: int = 8193) -> torch.Tensor:
    """Allowed stamp sides: every odd size up to 15, then odd sizes ~15 % apart (at most ~30 %
    more pixels than the footprint needs)."""
    sides = list(range(3, 16, 2))
    while sides[-1] < limit:
        nxt = int(math.ceil(sides[-1] * 1.15))
        sides.append(nxt + 1 - nxt % 2)
    return torch.tensor(sides)


SIDES = _allowed_sides()
_MIP_CACHE: dict = {}
_ATLAS_CACHE: dict = {}


def mip_pyramid(lib: TemplateLibrary, dtype: torch.dtype, device) -> list:
    """The template library and its 2x2-averaged reductions while the side stays even and >= 4.
    Shape: list of (T, 1, R_L, R_L)."""
    key = (lib.digest, lib.name, dtype, str(device))
    if key not in _MIP_CACHE:
        level = lib.alphas.to(device=device, dtype=dtype)[:, None]
        levels = [level]
        while level.shape[-1] % 2 == 0 and level.shape[-1] >= 4:
            level = F.avg_pool2d(level, 2)
            levels.append(level)
        if len(_MIP_CACHE) > 16:
            _MIP_CACHE.clear()
        _MIP_CACHE[key] = levels
    return _MIP_CACHE[key]


@dataclass
class Atlas:
    """Every mip level of every template in one image, each with a zero border of at least one
    pixel. Shape: image (1, 1, Ha, Wa); x0 (T,) and y0 (T, L) float64, the atlas position of
    template t's pixel (0, 0) at level L; res (L,) float64 each level's side."""

    image: torch.Tensor
    x0: torch.Tensor
    y0: torch.Tensor
    res: torch.Tensor


def atlas(lib: TemplateLibrary, dtype: torch.dtype, device) -> Atlas:
    """The library's :class:`Atlas` (cached): templates on a near-square grid of cells, each
    cell holding the template's levels one above the other."""
    key = (lib.digest, lib.name, dtype, str(device))
    if key not in _ATLAS_CACHE:
        levels = mip_pyramid(lib, dtype, device)
        sides = [lv.shape[-1] for lv in levels]
        cell_w = sides[0] + 2
        tops = [sum(s + 2 for s in sides[:i]) + 1 for i in range(len(sides))]
        cell_h = sum(s + 2 for s in sides)
        count = lib.count
        cols = max(1, math.ceil(math.sqrt(count * cell_h / cell_w)))
        rows = math.ceil(count / cols)
        image = torch.zeros(rows * cell_h, cols * cell_w, dtype=dtype, device=device)
        x0, y0 = [], []
        for t in range(count):
            r, c = divmod(t, cols)
            x0.append(c * cell_w + 1)
            y0.append([r * cell_h + top for top in tops])
            for lv, top, s in zip(levels, tops, sides):
                image[r * cell_h + top:r * cell_h + top + s, c * cell_w + 1:c * cell_w + 1 + s] = \
                    lv[t, 0]
        f64 = torch.float64
        if len(_ATLAS_CACHE) > 16:
            _ATLAS_CACHE.clear()
        _ATLAS_CACHE[key] = Atlas(image=image[None, None], x0=torch.tensor(x0, dtype=f64,
                                                                            device=device),
                                  y0=torch.tensor(y0, dtype=f64, device=device).view(count, -1),
                                  res=torch.tensor(sides, dtype=f64, device=device))
    return _ATLAS_CACHE[key]


def floor_log2(x: torch.Tensor) -> torch.Tensor:
    """``floor(log2(x))`` for x > 0, exactly: from the binary exponent (``x = m 2^e``, m in
    [0.5, 1)), not from a logarithm, whose last bit differs between the CPU's and CUDA's
    libraries (a footprint whose ratio to the template is a power of two then took another mip
    level on CUDA). Shape: (E,) float -> (E,) int64."""
    return (torch.frexp(x)[1] - 1).long()


def stamp_geometry(footprint: torch.Tensor, defocus: torch.Tensor, resolution: int,
                   level_count: int, coarse_side: Optional[int] = COARSE_SIDE) -> tuple:
    """Each entry's stamp layout from its footprint (pixels, float64, >= 1) and defocus radius.

    Stamps at least ``coarse_side`` pixels wide (template plus defocus) go to a grid ``f = 2**L``
    times coarser (f the largest power of two up to ``2**COARSE_MAX_LEVEL`` keeping them >=
    COARSE_MIN_SIDE coarse pixels wide), footprint and radius divided by f. Returns
    ``(footprint, radius, coarse, side, sub, level, phases)``, all (E,): the footprint on its
    grid, the disc-blur radius (0: none; radii <= 1 do not blur on the image grid), the grid
    level L, the stamp side before the blur (an allowed side covering every pixel the
    footprint's disc reaches), the supersampling per axis, the mip level (no finer than twice
    the footprint) and the phases P per axis (``sub`` for small stamps without a blur: they are
    sampled at every 1 / P pixel; 1 otherwise).
    """
    radius = torch.where(defocus > 1, defocus, torch.zeros_like(defocus))
    coarse = torch.zeros_like(radius)
    full = footprint + 2 * radius
    if coarse_side is not None and bool((full >= coarse_side).any()):
        coarse = torch.where(full >= coarse_side,
                             floor_log2(full / COARSE_MIN_SIDE)
                             .clamp(1, COARSE_MAX_LEVEL),
                             torch.zeros_like(full)).long()
        factor = (2.0 ** coarse).to(torch.float64)
        footprint = (footprint / factor).clamp(min=1.0)
        radius = torch.where(coarse > 0, torch.floor(radius / factor + 0.5).long(), radius)
    # every pixel the footprint's disc reaches (partly covered ones are box-filtered)
    raw_side = 2 * torch.floor(footprint / 2 + 0.5).clamp(min=1).long() + 1
    sides = SIDES.to(footprint.device)
    side = sides[torch.searchsorted(sides, raw_side)]
    sub = torch.where(side <= 5, 4, torch.where(side <= PHASE_SIDE, 2, 1))
    level = floor_log2(resolution / (footprint * sub)) \
        .clamp(0, level_count - 1).long()
    phases = torch.where(radius == 0, sub, torch.ones_like(sub))
    return footprint, radius, coarse, side, sub, level, phases


def defocus_brighten(blurred: torch.Tensor) -> torch.Tensor:
    """The depth-of-field alpha of a disc-blurred template: ``min(1, (2 b)^(1/3))``.

    The blur spreads a particle's alpha thin; doubling it and taking the cube root brings it
    back up (near, out-of-focus particles look like large soft discs rather than vanishing),
    as the paper's research code does. Shape: any -> same.
    """
    return torch.exp(torch.log((2 * blurred).clamp(min=0)) / 3).clamp(max=1)


#: Taps of the disc of radius r (integer offsets with dx² + dy² <= r²) for r = 0 .. 255 (the
#: defocus radii a record can store).
DISC_TAPS = [sum(2 * math.isqrt(r * r - a * a) + 1 for a in range(-r, r + 1)) for r in range(256)]
_CONSTANTS: dict = {}


def _constant(name: str, values, dtype, device) -> torch.Tensor:
    """A small constant tensor, made once per dtype and device."""
    key = (name, dtype, str(device))
    if key not in _CONSTANTS:
        _CONSTANTS[key] = torch.tensor(values, dtype=dtype, device=device)
    return _CONSTANTS[key]


def disc_counts(radius: torch.Tensor) -> torch.Tensor:
    """Taps of the disc of each radius r (integer offsets with dx² + dy² <= r²).
    Shape: (n,) int64 -> (n,) float64."""
    return _constant("taps", DISC_TAPS, torch.float64, radius.device).index_select(0, radius)


def soft_box(radius: int) -> int:
    """Width ``b`` (odd, pixels) of the boxes whose square ``b x b`` applied twice softens a
    brightened stamp of defocus radius r: ``2 (floor(r / 4) + 2) + 1`` (5 for r = 2, 3; 7 for
    r = 4 .. 7; 15 for r = 20). Twice a box is a tent per axis, of standard deviation
    ``sqrt((b² − 1) / 6)`` (2.0, 2.8, 6.1 pixels). The cube root of the brightening has an
    infinite slope at b = 0, so the faint outer ring of the disc blur becomes a rim one or two
    pixels wide; the tent spreads it over a ramp while keeping the rule's total light (the boxes
    are normalised, the stamp grows by ``b − 1`` on each side)."""
    return 2 * (radius // 4 + 2) + 1


#: A softened stamp's blur samples may lie this share of ``b − 1`` apart (``StampSet.gap``):
#: the sum of copies of the tent ``b x b`` box twice, ``(b − 1) / 2`` pixels apart, ripples by
#: a few per mille of its light (a few grey levels at most on the bench scene's sparks).
GAP_SHARE = 0.5
#: Box widths for r = 0 .. 255 (the defocus radii a record can store).
SOFT_BOX = [soft_box(r) for r in range(256)]


@dataclass
class StampSet:
    """The stamps of E entries, ragged: entry e's stamp, ``side x side`` pixels with a one-pixel
    zero border around it, sampled every ``1 / P`` pixel (P = ``phases[e]``): the stamp's
    value at ``(y, x) / P − (side + 1) / 2`` pixels from the particle's centre (row, column of
    the ``n x n`` grid, ``n = P (side + 1) + 1``; its outer rows and columns are the zero
    border) is at ``pixels[first[e] + y n + x]``. With P = 1 that is the stamp's pixels with
    their border.

    ``gap``: how far apart (image pixels) an entry's blur samples may lie along its streak
    without a visible ripple (:func:`~weathergen.engine.tracks.streak_samples`): ``(b − 1) / 2``
    of its grid's pixels for a softened stamp (smooth over the box ``b``, :func:`soft_box`),
    one of its grid's pixels otherwise.

    Reusable while the looks stay fixed (e.g. the paper's particles across attack steps).
    Shape: pixels (L,) in the images' dtype; first, side (odd), coarse (the grid level),
    phases (E,) int64; gap (E,) float64.
    """

    pixels: torch.Tensor
    first: torch.Tensor
    side: torch.Tensor
    coarse: torch.Tensor
    phases: torch.Tensor
    gap: torch.Tensor

    @property
    def count(self) -> int:
        return int(self.side.numel())

    def to(self, dtype: torch.dtype, device=None) -> "StampSet":
        device = self.pixels.device if device is None else device
        return StampSet(pixels=self.pixels.to(device=device, dtype=dtype),
                        first=self.first.to(device), side=self.side.to(device),
                        coarse=self.coarse.to(device), phases=self.phases.to(device),
                        gap=self.gap.to(device))

    @staticmethod
    def cat(parts: Sequence["StampSet"]) -> "StampSet":
        offsets = [0]
        for p in parts[:-1]:
            offsets.append(offsets[-1] + int(p.pixels.numel()))
        return StampSet(pixels=torch.cat([p.pixels for p in parts]),
                        first=torch.cat([p.first + o for p, o in zip(parts, offsets)]),
                        side=torch.cat([p.side for p in parts]),
                        coarse=torch.cat([p.coarse for p in parts]),
                        phases=torch.cat([p.phases for p in parts]),
                        gap=torch.cat([p.gap for p in parts]))


def build(looks: Looks, lib: TemplateLibrary, *, dtype: torch.dtype = torch.float32,
          coarse_side: Optional[int] = COARSE_SIDE,
          chunk_elements: int = STAMP_CHUNK_ELEMENTS) -> StampSet:
    """Every entry's stamp (see the module doc). Shape: E entries -> :class:`StampSet`."""
    device = looks.template.device
    if looks.count and (int(looks.template.min()) < 0 or int(looks.template.max()) >= lib.count):
        raise ConfigError(f"particle template index out of range for the {lib.count} "
                          f"templates of '{lib.name}'")
    with torch.no_grad():
        book = atlas(lib, dtype, device)
        footprint, radius, coarse, side, sub, level, phases = stamp_geometry(
            looks.footprint.to(torch.float64), looks.defocus, lib.resolution,
            int(book.res.numel()), coarse_side)
        # brightened blurred stamps are softened afterwards and grow by the kernel's reach
        soft = looks.brighten & (radius > 0)
        box = _constant("box", SOFT_BOX, torch.int64, device).index_select(0, radius)
        grow = torch.where(soft, box - 1, torch.zeros_like(radius))
        inner = side + 2 * radius
        full = inner + 2 * grow
        fine = phases * (full + 1) + 1     # grid side with the border (phases > 1: no blur)
        block = fine * fine
        first = starts(block)
        size = int(block.sum()) if looks.count else 0
        # One float64 buffer: every stamp in its bordered place, then, for the stamps to blur,
        # their rows before the blur, one per row of ``width`` values: 2 r zeros, the row, 2 r
        # zeros (so that every box of the blur lies inside it): the sampled pixels go straight
        # where they belong, and a row's prefix sums are the cumulative sum of its values.
        blurred = radius > 0
        rows = torch.where(blurred, side, torch.zeros_like(side))
        rows_first = starts(rows)
        width = int((side + 4 * radius).max()) + 1 if bool(blurred.any()) else 1
        work = torch.zeros(size + int(rows.sum()) * width if looks.count else 0,
                           dtype=torch.float64, device=device)
        # pixel (y, x) of entry e goes to ``place[e] + y * pitch[e] + x``
        place = torch.where(blurred, size + rows_first * width + 2 * radius + 1,
                            first + full + 3)      # (unblurred stamps do not grow)
        pitch = torch.where(blurred, torch.full_like(side, width), full + 2)
        # stamps brightened without a blur (a defocus radius that rounds to 0 on a coarse grid)
        bright = looks.brighten & ~blurred
        coef = _coefficients(looks, book, footprint, side, level, dtype)
        _sample(coef, book, side, sub, place, pitch, work, bright if bool(bright.any()) else None,
                chunk_elements, phases == 1)
        _sample_phases(coef, book, side, phases, first, work, chunk_elements)
        if bool(blurred.any()):
            members = torch.nonzero(blurred).squeeze(1)
            # each row divided by its disc's taps (the blur's normalisation, linear), then
            # summed up
            rows_of = torch.repeat_interleave(disc_counts(radius.index_select(0, members)),
                                              side.index_select(0, members))
            prefix = work[size:].view(-1, width).div_(rows_of[:, None]).cumsum_(1).view(-1)
            _blur(prefix, members, side, radius, looks.brighten, rows_first, width,
                  first + grow * (full + 2) + grow, full, inner, work, chunk_elements)
        if bool(soft.any()):
            _soften(work, torch.nonzero(soft).squeeze(1), first, inner, box, full,
                    chunk_elements)
        # softened stamps are smooth over the box: blur samples may lie (b - 1) / 2 of their
        # grid's pixels apart; the others one pixel (both times the grid's factor)
        gap = torch.where(soft, (box - 1).to(torch.float64) * GAP_SHARE, 1.0) * 2.0 ** coarse
    return StampSet(pixels=work[:size].to(dtype), first=first, side=full, coarse=coarse,
                    phases=phases, gap=gap)


def _coefficients(looks: Looks, book: Atlas, footprint, side, level, dtype) -> torch.Tensor:
    """Per entry, how a sample at (gx, gy) pixels from the stamp's centre reads the atlas.
    Shape: (E, 8), see :func:`_sample`."""
    # A sample at (gx, gy) pixels from the stamp's centre reads the atlas at the
    # normalised position (bx + ax gx + cx gy, by + ay gx + cy gy): the template at
    # Rot(−rotation) (gx, gy) in units of half the footprint (so image offset = Rot(rotation) ·
    # template offset), grid_sample's pixel convention (align_corners=False). It is inside the
    # disc when gx² + gy² <= (footprint / 2)² (1 + RIM_MARGIN).
    height, width = book.image.shape[-2:]
    res = book.res.index_select(0, level)
    scale = res / footprint
    cos, sin = torch.cos(looks.rotation), torch.sin(looks.rotation)
    x0 = book.x0.index_select(0, looks.template)
    y0 = book.y0.view(-1).index_select(0, looks.template * book.y0.shape[1] + level)
    coef = torch.stack(((2 * x0 + res) / width - 1, 2 * scale * cos / width,
                        2 * scale * sin / width, (2 * y0 + res) / height - 1,
                        -2 * scale * sin / height, 2 * scale * cos / height,
                        (footprint / 2) ** 2 * (1.0 + RIM_MARGIN),
                        -((side - 1) // 2).to(torch.float64)), 1).to(dtype)
    return coef


def _sample(coef: torch.Tensor, book: Atlas, side, sub, place, pitch, work: torch.Tensor,
            bright: Optional[torch.Tensor], chunk: int, whole: torch.Tensor) -> None:
    """The stamps sampled at whole pixels (``whole`` (E,): one phase), before their blur,
    written to ``work`` (pixel (y, x) of entry e at ``place[e] + y pitch[e] + x``): each pixel
    the mean of its ``sub x sub`` bilinear samples of the template's mip level at the rotated and
    scaled position, zero outside the footprint's disc; brightened where ``bright`` (E,) says
    so."""
    if side.numel() == 0 or not bool(whole.any()):
        return
    device, dtype = coef.device, coef.dtype
    # entries by supersampling factor (4, 2, 1), then one item per stamp row, the groups' rows one
    # after the other: its entry, its row y and where its pixel 0 goes in ``work`` (a pixel's
    # column is then its index in the item)
    groups = [(f, torch.nonzero((sub == f) & whole).squeeze(1)) for f in (4, 2, 1)]
    groups = [(f, m) for f, m in groups if m.numel()]
    order = torch.cat([m for _, m in groups]) if len(groups) > 1 else groups[0][1]
    s = side.index_select(0, order)
    ends = torch.cumsum(s, 0)
    last = list(itertools.accumulate(int(m.numel()) for _, m in groups))
    cuts = [0] + ends.index_select(0, torch.tensor(last, device=device) - 1).tolist()
    rows = cuts[-1]
    row_entry = torch.repeat_interleave(order, s, output_size=rows)
    row_y = torch.arange(rows, device=device) \
        - torch.repeat_interleave(ends - s, s, output_size=rows)
    row_size, row_place, row_pitch = torch.stack((side, place, pitch)).index_select(1, row_entry)
    row_at = torch.addcmul(row_place, row_y, row_pitch)
    for g, (factor, _) in enumerate(groups):
        # sample offsets in a pixel along one axis: (sub, 1); a pixel's sub² samples are
        # row-major, (sub rows, sub columns), so a sample's x depends on its column alone and its
        # y on its row: the coordinates are computed per axis (sub, n) and broadcast
        offsets = _constant(f"offsets{factor}", [[(k + 0.5) / factor - 0.5]
                                                 for k in range(factor)], dtype, device)
        row_offsets = _constant(f"row_offsets{factor}", [[[(k + 0.5) / factor - 0.5]]
                                                         for k in range(factor)], dtype, device)
        lo, hi = cuts[g], cuts[g + 1]
        for item, col in runs(row_size[lo:hi], max(1, chunk // (factor * factor))):
            if lo:
                item = item + lo
            e = row_entry.index_select(0, item)
            row = row_y.index_select(0, item)
            bx, ax, cx, by, ay, cy, rho2, centre = coef.index_select(0, e).t()
            gx = (col.to(dtype) + centre) + offsets             # (sub columns, n)
            gy = (row.to(dtype) + centre) + row_offsets         # (sub rows, 1, n)
            n = gx.shape[-1]
            grid = torch.empty(factor, factor, n, 2, dtype=dtype, device=device)
            grid_x, grid_y = grid.unbind(-1)
            torch.addcmul(torch.addcmul(bx, ax, gx), cx, gy, out=grid_x)
            torch.addcmul(torch.addcmul(by, ay, gx), cy, gy, out=grid_y)
            inside = torch.addcmul(gx * gx, gy, gy) <= rho2
            value = F.grid_sample(book.image, grid.view(1, factor * factor, n, 2),
                                  mode="bilinear", padding_mode="zeros",
                                  align_corners=False).view(inside.shape) * inside
            while value.numel() > n:         # pairwise, in a fixed order: the same bits anywhere
                value = value.view(2, -1, n).sum(0)
            value = value.view(-1)
            if factor > 1:
                value = value / (factor * factor)
            if bright is not None:      # (only the pixels of the stamps it brightens)
                which = torch.nonzero(bright.index_select(0, e)).squeeze(1)
                value.index_copy_(0, which, defocus_brighten(value.index_select(0, which)))
            work.index_copy_(0, row_at.index_select(0, item) + col, value.to(torch.float64))


def _sample_phases(coef: torch.Tensor, book: Atlas, side, phases, first, work: torch.Tensor,
                   chunk: int) -> None:
    """The phase stamps (``phases`` P > 1), written to their bordered places in ``work``: the
    value at ``(y, x) / P`` pixels on the grid around the centre is the mean of the template over
    the pixel square centred there (``P x P`` bilinear samples of the mip level at every 1 / P
    pixel, zero outside the footprint's disc), i.e. the pixel-integrated template at every
    1 / P of a pixel.

    Per stamp side s (and so per P), the entries' samples are one dense batch of ``m x m``
    samples (``m = P (s + 2)`` per axis, centred on the particle), averaged over every ``P x P``
    window (:func:`_window_mean`): ``n = P (s + 1) + 1`` values per axis, exactly the entry's bordered grid, copied
    whole to its place."""
    if side.numel() == 0:
        return
    dtype, device = coef.dtype, coef.device
    candidates = torch.nonzero(phases > 1).squeeze(1)
    if candidates.numel() == 0:
        return
    sizes = torch.unique(side.index_select(0, candidates)).tolist()
    for s in sizes:
        members = candidates.index_select(
            0, torch.nonzero(side.index_select(0, candidates) == s).squeeze(1))
        factor = PHASE_FACTORS[s]
        c = coef.index_select(0, members)[:, :, None, None]
        m = factor * (s + 2)
        n = m - factor + 1
        # sample offsets from the centre, pixels: (b − (m − 1) / 2) / P, along x and along y
        gx = _constant(f"gx{factor},{m}", [[[(b - (m - 1) / 2) / factor for b in range(m)]]],
                       dtype, device)
        gy = _constant(f"gy{factor},{m}", [[[(b - (m - 1) / 2) / factor] for b in range(m)]],
                       dtype, device)
        steps = _constant(f"steps{n}", list(range(n * n)), torch.int64, device)
        per = max(1, chunk // (m * m))
        for lo in range(0, int(members.numel()), per):
            bx, ax, cx, by, ay, cy, rho2, _ = c[lo:lo + per].unbind(1)
            count = bx.shape[0]
            grid = torch.empty(count, m, m, 2, dtype=dtype, device=device)
            grid_x, grid_y = grid.unbind(-1)
            torch.addcmul(torch.addcmul(bx, ax, gx), cx, gy, out=grid_x)
            torch.addcmul(torch.addcmul(by, ay, gx), cy, gy, out=grid_y)
            value = F.grid_sample(book.image, grid.view(1, count * m, m, 2), mode="bilinear",
                                  padding_mode="zeros", align_corners=False).view(count, m, m)
            value.mul_(torch.addcmul(gx * gx, gy, gy) <= rho2)
            value = _window_mean(value, factor)                           # (count, n, n)
            at = first.index_select(0, members[lo:lo + per])[:, None] + steps
            work.index_copy_(0, at.view(-1), value.reshape(-1).to(torch.float64))


def _window_mean(value: torch.Tensor, factor: int) -> torch.Tensor:
    """The mean of every ``factor x factor`` window (stride 1) of each ``m x m`` array, summed
    separably and pairwise (columns, then rows: windows of 2, then of 4 as two adjacent windows
    of 2), divided by ``factor²`` (a power of two: exact). Each output is the same arithmetic
    on its own 16 (or 4) inputs wherever it lies. Shape: (E, m, m) -> (E, m − P + 1, m − P + 1).
    """
    width = 1
    while width < factor:
        value = value[..., :-width] + value[..., width:]
        width *= 2
    width = 1
    while width < factor:
        value = value[:, :-width] + value[:, width:]
        width *= 2
    return value / (factor * factor)


def _blur(prefix, members, side, radius, brighten, rows_first, width, first, full, inner,
          work, chunk: int) -> None:
    """Disc-blurred (and brightened where flagged) stamps ``members`` from their rows' prefix
    sums (already divided by the disc's taps) into their bordered places in ``work``: the
    ``inner x inner`` blurred stamp with its top-left pixel at ``first + full + 3`` (``first``
    is shifted where a stamp grows for its softening; ``full + 2`` is the row pitch).

    The blurred pixel (Y, X) of a stamp of side s and radius r sums, over the disc's rows
    ``a`` in [−r, r] of half-width ``w = floor(sqrt(r² − a²))``, the stamp's row
    ``y = Y − r − a`` between columns ``X − r − w`` and ``X − r + w``. So every (entry, stamp row
    y, disc row a) is a *segment* that adds box sums of row y (differences of its prefix sums;
    the row's 2 r zeros on either side hold every box) to the ``s + 2 w`` columns of output row
    ``y + r + a`` it reaches, from column ``r − w`` on.
    """
    s, r = side.index_select(0, members), radius.index_select(0, members)
    f = full.index_select(0, members)
    taps = 2 * r + 1
    item, local = next(runs(s * taps, 1 << 62))                 # the segments, all at once
    per = torch.stack((r, s, taps, rows_first.index_select(0, members),
                       first.index_select(0, members), f)).index_select(1, item)
    rr, ss, tt, row_first, at0, ff = per
    y = torch.div(local, tt, rounding_mode="floor")
    a = local - y * tt - rr
    w = torch.floor(torch.sqrt((rr * rr - a * a).to(torch.float64))).long()
    base = (row_first + y) * width + 2 * rr
    # bordered output pixel (Y + 1, X + 1) of row Y = y + r + a from column X = r − w on
    at = at0 + (y + rr + a + 1) * (ff + 2) + rr - w + 1
    # element x of a segment: the box over the row's columns x − 2 w .. x
    # (rows of a stacked table: gathering them is several times faster than along a second axis)
    consts = torch.stack((base + 1, base - 2 * w, at), 1)
    for seg, x in runs(ss + 2 * w, chunk):
        c_hi, c_lo, c_out = consts.index_select(0, seg).add_(x[:, None]).t()
        work.index_add_(0, c_out, prefix.index_select(0, c_hi) - prefix.index_select(0, c_lo))
    flags = brighten.index_select(0, members)
    if bool(flags.any()):
        bright = members.index_select(0, torch.nonzero(flags).squeeze(1))
        nb = inner.index_select(0, bright)
        for e, local in runs(nb * nb, chunk):
            ne = nb.index_select(0, e)
            row = torch.div(local, ne, rounding_mode="floor")
            at = first.index_select(0, bright.index_select(0, e)) \
                + (row + 1) * (full.index_select(0, bright.index_select(0, e)) + 2) \
                + local - row * ne + 1
            work.index_copy_(0, at, defocus_brighten(work.index_select(0, at)))


def _soften(work, members, first, inner, box, full, chunk: int) -> None:
    """Soften the brightened stamps ``members`` in place: each holds its ``n x n`` stamp
    (n = ``inner``) at offset ``b − 1`` inside its bordered ``(full + 2)²`` block (``full =
    n + 2 (b − 1)``, b = ``box``); afterwards the whole ``full x full`` is the stamp convolved
    with a normalised, centred ``b x b`` box twice (:func:`soft_box`).

    The stamps go in groups of similar sides (:func:`_soften_groups`: largest first, each group's
    canvases at most ``chunk`` values or at most 1.5 times its stamps' own pixels), so that the
    work stays proportional to the stamps' pixels, not to the count times the largest. Per group
    the stamps are copied, each on its own canvas at the top left, into one zero-filled dense
    float64 array ``(M, F, F)`` (F the group's largest ``full``); each of the four box passes
    (rows, rows, columns, columns) takes cumulative sums along its axis (per row or column: its
    sums do not depend on the other stamps, nor on F or the padding, which only add leading or
    trailing exact zeros) and differences them at the stamp's own half-width h:
    ``out[x] = S[x + h] − S[x − h − 1]`` (divided by ``b⁴`` at the end). The boxes reach at
    most ``b − 1`` beyond the stamp, so they stay inside its canvas; where a span is all zeros
    the difference is exactly zero.
    """
    sides = full.index_select(0, members)
    order = torch.argsort(sides, descending=True, stable=True)
    for lo, hi in _soften_groups(sides.index_select(0, order).tolist(), chunk):
        _soften_group(work, members.index_select(0, order[lo:hi]), first, inner, box, full,
                      chunk)


#: A softening group's canvases hold at most this many times its stamps' own pixels (or at
#: most ``chunk`` values).
SOFTEN_WASTE = 1.5


def _soften_groups(sides: list, chunk: int) -> list:
    """``(lo, hi)`` index ranges of ``sides`` (descending) whose padded canvases
    ``(hi − lo) · sides[lo]²`` stay within ``max(chunk, SOFTEN_WASTE · Σ side²)``; a single
    stamp always forms a group."""
    groups, lo = [], 0
    while lo < len(sides):
        largest, own, hi = sides[lo] ** 2, 0, lo
        while hi < len(sides):
            own += sides[hi] ** 2
            if hi > lo and (hi - lo + 1) * largest > max(chunk, SOFTEN_WASTE * own):
                break
            hi += 1
        groups.append((lo, hi))
        lo = hi
    return groups


def _soften_group(work, members, first, inner, box, full, chunk: int) -> None:
    """One group of :func:`_soften`."""
    device = work.device
    m = int(members.numel())
    n, b = inner.index_select(0, members), box.index_select(0, members)
    f = full.index_select(0, members)
    top = first.index_select(0, members) + f + 3                       # bordered pixel (1, 1)
    side = int(f.max())
    dense = torch.zeros(m, side, side, dtype=torch.float64, device=device)
    flat = dense.view(-1)
    for e, local in runs(n * n, chunk):
        ne, off = n.index_select(0, e), b.index_select(0, e) - 1
        y = torch.div(local, ne, rounding_mode="floor")
        x = local - y * ne
        flat.index_copy_(0, (e * side + y + off) * side + x + off,
                         work.index_select(0, top.index_select(0, e) + (y + off)
                                           * (f.index_select(0, e) + 2) + x + off))
    half = (b - 1) // 2
    pad = int(half.max()) + 1
    # out[x] = S[hi] − S[lo] in the padded sums: hi = x + pad + h, lo = hi − b
    hi = torch.arange(side, device=device)[None] + (pad + half)[:, None]
    lo = hi - b[:, None]
    ends = {2: (hi[:, None], lo[:, None]), 1: (hi[:, :, None], lo[:, :, None])}
    for axis in (2, 2, 1, 1):
        sums = F.pad(dense, (pad, pad, 0, 0) if axis == 2 else (0, 0, pad, pad)).cumsum_(axis)
        hi_a, lo_a = ends[axis]
        dense = sums.gather(axis, hi_a.expand(dense.shape)) \
            - sums.gather(axis, lo_a.expand(dense.shape))
    dense = dense / (b.to(torch.float64) ** 4)[:, None, None]      # the four boxes' 1 / b
    flat = dense.reshape(-1)
    for e, local in runs(f * f, chunk):
        fe = f.index_select(0, e)
        y = torch.div(local, fe, rounding_mode="floor")
        x = local - y * fe
        work.index_copy_(0, top.index_select(0, e) + y * (fe + 2) + x,
                         flat.index_select(0, (e * side + y) * side + x))
