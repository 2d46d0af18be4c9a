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

- samples: every stamp pixel's ``sub x sub`` sample positions are computed for all entries at
  once (with a GPU's chunks; group by supersampling factor with the CPU's) and read with one
  ``grid_sample`` from an atlas holding every mip level of every template (one-pixel zero
  borders between them, so a read never bleeds into a neighbour); entries of several template
  libraries (:func:`build_many`) are built together, only the reads going library by library;
- disc blur: the disc is a stack of rows of half-width ``w(dy)``; a blurred pixel sums, over the
  disc's rows, box sums of the stamp's rows, each the difference of two prefix sums. Prefix sums
  are taken per stamp row (never across stamps, so a stamp does not depend on the others), in
  float64 (where a row is all zeros the difference is exactly zero: blurred stamps stay exactly
  zero outside their support);
- phase stamps: samples at every 1 / P pixel (all sides in one ragged pass with a GPU's
  chunks, one dense batch per side with the CPU's), averaged over P x P windows (separable
  pairwise sums) and copied to the stamps' places;
- softening: stamps grouped by similar sides (work proportional to their pixels, not to the
  count times the largest), disc-blurred straight onto their group's canvases, four box passes
  per group, each along one axis of every stamp at
  once (differences of per-row or per-column prefix sums in float64, as the disc blur).

Elementwise operations are those whose result does not depend on an element's position in its
tensor (``exp``/``log`` rather than ``pow`` and ``sigmoid``, whose vectorised and scalar CPU
kernels round differently), so a stamp is the same whatever other stamps the call holds.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Optional, Sequence, Union

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
#: Chunks of at least this many elements (a GPU's) sample the stamps of every supersampling,
#: and the phase stamps of every side, in one ragged pass each, and brighten whole softening
#: canvases (fewer operations); smaller ones (the CPU's) go group by group, in dense arrays
#: (less memory traffic). The same bytes either way.
RAGGED_CHUNK = 1 << 20
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
#: Per allowed side s: ``(s − 1) / 2 + 1``, and (s, its supersampling: 4 up to 5 pixels, 2 up to
#: PHASE_SIDE, then 1).
SIDE_STEPS = [(s - 1) / 2 + 1 for s in SIDES.tolist()]
SIDE_TABLE = [SIDES.tolist(),
              [4 if s <= 5 else 2 if s <= PHASE_SIDE else 1 for s in SIDES.tolist()]]
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


def stamp_geometry(footprint: torch.Tensor, defocus: torch.Tensor,
                   resolution: Union[int, torch.Tensor], level_count: Union[int, torch.Tensor],
                   coarse_side: Optional[int] = COARSE_SIDE,
                   allowed: Optional[torch.Tensor] = None) -> tuple:
    """Each entry's stamp layout from its footprint (pixels, float64, >= 1) and defocus radius.

    Stamps at least ``coarse_side`` pixels wide (template plus defocus) go to a grid ``f = 2**L``
    times coarser (f the largest power of two up to ``2**COARSE_MAX_LEVEL`` keeping them >=
    COARSE_MIN_SIDE coarse pixels wide), footprint and radius divided by f. Returns
    ``(footprint, radius, coarse, side, sub, level, phases)``, all (E,): the footprint on its
    grid, the disc-blur radius (0: none; radii <= 1 do not blur on the image grid), the grid
    level L, the stamp side before the blur (an allowed side covering every pixel the
    footprint's disc reaches), the supersampling per axis, the mip level (no finer than twice
    the footprint) and the phases P per axis (``sub`` for small stamps without a blur: they are
    sampled at every 1 / P pixel; 1 otherwise). ``resolution`` and ``level_count``: the
    template library's side and mip levels, or per entry (E,) (float64, int64) where the
    entries come from several libraries. ``allowed`` (E,) bool: the entries that may go to a
    coarser grid (None: all).
    """
    radius = defocus.masked_fill(defocus <= 1, 0)
    coarse = torch.zeros_like(radius)
    full = torch.add(footprint, radius, alpha=2)
    large = full >= coarse_side if coarse_side is not None else None
    if large is not None and allowed is not None:
        large &= allowed
    if large is not None and bool(large.any()):
        coarse = torch.where(large,
                             floor_log2(full / COARSE_MIN_SIDE)
                             .clamp(1, COARSE_MAX_LEVEL),
                             torch.zeros_like(full)).long()
        factor = (2.0 ** coarse).to(torch.float64)
        footprint = (footprint / factor).clamp(min=1.0)
        radius = torch.where(coarse > 0, torch.floor(radius / factor + 0.5).long(), radius)
    # every pixel the footprint's disc reaches (partly covered ones are box-filtered): the
    # first allowed side s >= 2 max(1, floor(footprint / 2 + 0.5)) + 1, i.e. the first whose
    # (s − 1) / 2 + 1 exceeds footprint / 2 + 0.5
    steps = _constant("side_steps", SIDE_STEPS, torch.float64, footprint.device)
    at = torch.searchsorted(steps, footprint / 2 + 0.5, right=True)
    side, sub = _constant("sides", SIDE_TABLE, torch.int64, footprint.device) \
        .index_select(1, at).unbind(0)
    # (the template's resolution over the footprint as ``int / tensor`` computes it: times the
    # reciprocal)
    level = floor_log2((footprint * sub).reciprocal() * resolution)
    level = level.clamp(0, level_count - 1) if isinstance(level_count, int) \
        else torch.minimum(level.clamp(min=0), level_count - 1)
    phases = sub.masked_fill(radius > 0, 1)
    return footprint, radius, coarse, side, sub, level, phases


def defocus_brighten(blurred: torch.Tensor) -> torch.Tensor:
    """The depth-of-field alpha of a disc-blurred template: ``min(1, (2 b)^(1/3))``.

    The blur spreads a particle's alpha thin; doubling it and taking the cube root brings it
    back up (near, out-of-focus particles look like large soft discs rather than vanishing),
    as the paper's research code does. Shape: any -> same.
    """
    return torch.exp(torch.log((2 * blurred).clamp(min=0)) / 3).clamp(max=1)


#: ``−((s − 1) // 2)`` for every stamp side s (a stamp's pixel 0 from its centre).
CENTRES = [float(-((s - 1) // 2)) for s in range(int(SIDES[-1]) + 1)]
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
#: A softened stamp's blur-sample gap per radius, ``(b − 1) · GAP_SHARE`` grid pixels, and
#: each grid level's factor ``2**L`` (image pixels per grid pixel).
GAPS = [(b - 1) * GAP_SHARE for b in SOFT_BOX]
FACTORS = [2.0 ** level for level in range(COARSE_MAX_LEVEL + 1)]
#: ``floor(sqrt(d))`` for d = 0 .. 255² (the half-widths of the disc's rows).
ISQRT = [math.isqrt(d) for d in range(255 * 255 + 1)]
#: Per box width b: ``b⁴`` (the four box passes' normalisation).
BOX4 = [float(b) ** 4 for b in range(2 * (255 // 4 + 2) + 2)]


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


def stored(images: torch.Tensor, *, dtype: torch.dtype = torch.float32, device=None) -> StampSet:
    """Stamps given as images (a record's stored stamps, see
    :class:`~weathergen.engine.Particles`): each drawn at its native pixels (P = 1, the image
    grid), its centre pixel on the particle, a one-pixel zero border around it. Their ``gap`` is
    infinite, so that a streak keeps the record's own number of blur samples, as the research code
    that stored them draws it (:func:`~weathergen.engine.tracks.streak_samples`).
    Shape: images (E, S, S), S odd -> :class:`StampSet` of E entries."""
    images = images.detach().to(device=device if device is not None else images.device, dtype=dtype)
    count, side = int(images.shape[0]), int(images.shape[-1])
    if images.dim() != 3 or images.shape[-2] != side or side % 2 == 0:
        raise ConfigError(f"stored stamps must be (N, S, S) with S odd, got {tuple(images.shape)}")
    dev = images.device
    framed = F.pad(images, (1, 1, 1, 1))
    area = (side + 2) ** 2
    return StampSet(pixels=framed.reshape(-1),
                    first=torch.arange(count, device=dev, dtype=torch.int64) * area,
                    side=torch.full((count,), side, dtype=torch.int64, device=dev),
                    coarse=torch.zeros(count, dtype=torch.int64, device=dev),
                    phases=torch.ones(count, dtype=torch.int64, device=dev),
                    gap=torch.full((count,), math.inf, dtype=torch.float64, device=dev))


def build(looks: Looks, lib: TemplateLibrary, *, dtype: torch.dtype = torch.float32,
          coarse_side: Optional[int] = COARSE_SIDE,
          chunk_elements: int = STAMP_CHUNK_ELEMENTS) -> StampSet:
    """Every entry's stamp (see the module doc). Shape: E entries -> :class:`StampSet`."""
    return build_many([(looks, lib)], dtype=dtype, coarse_side=coarse_side,
                      chunk_elements=chunk_elements)


def build_many(parts: Sequence[tuple[Looks, TemplateLibrary]], *,
               dtype: torch.dtype = torch.float32, coarse_side: Optional[int] = COARSE_SIDE,
               chunk_elements: int = STAMP_CHUNK_ELEMENTS) -> StampSet:
    """The stamps of several parts ``(looks, library)``, the parts' entries one after the other,
    in one pass: entry for entry the bytes of ``StampSet.cat([build(looks, lib) for looks, lib
    in parts])``, at the tensor operations of one build (only the template reads, one
    ``grid_sample`` per chunk, go per library: each library's atlas is its own image, and a
    read's normalised coordinates are those of its atlas). With the CPU's small chunks (below
    :data:`RAGGED_CHUNK`) consecutive parts of one library are built together and the others
    one after the other (the same bytes): splitting every chunk's reads by library costs more
    there than the operations it saves."""
    libs: list[TemplateLibrary] = []
    which = []
    for _, lib in parts:
        k = next((i for i, known in enumerate(libs)
                  if known is lib or (known.digest, known.name) == (lib.digest, lib.name)), None)
        if k is None:
            libs.append(lib)
            k = len(libs) - 1
        which.append(k)
    if len(libs) > 1 and chunk_elements < RAGGED_CHUNK:
        runs_of_one = [[part for part, _ in group]
                       for _, group in itertools.groupby(zip(parts, which), key=lambda pw: pw[1])]
        if len(runs_of_one) > 1:
            return StampSet.cat([build_many(run, dtype=dtype, coarse_side=coarse_side,
                                            chunk_elements=chunk_elements)
                                 for run in runs_of_one])
    looks = parts[0][0] if len(parts) == 1 else Looks.cat([p[0] for p in parts])
    device = looks.template.device
    for (part, lib) in parts:
        low, high = [t.tolist() for t in torch.aminmax(part.template)] if part.count \
            else (0, 0)
        if not 0 <= low <= high < lib.count:
            raise ConfigError(f"particle template index out of range for the {lib.count} "
                              f"templates of '{lib.name}'")
    with torch.no_grad():
        books = [atlas(lib, dtype, device) for lib in libs]
        if len(libs) == 1:
            lib_of, resolution, level_count = None, libs[0].resolution, int(books[0].res.numel())
        else:
            lib_of = torch.repeat_interleave(
                torch.tensor(which, device=device),
                torch.tensor([p[0].count for p in parts], device=device))
            resolution, level_count = torch.tensor(
                [[float(lib.resolution) for lib in libs], [b.res.numel() for b in books]],
                dtype=torch.float64, device=device).index_select(1, lib_of).unbind(0)
            level_count = level_count.long()
        footprint, radius, coarse, side, sub, level, phases = stamp_geometry(
            looks.footprint.to(torch.float64), looks.defocus, resolution, level_count,
            coarse_side, looks.coarse)
        # brightened blurred stamps are softened afterwards and grow by the kernel's reach
        blurred = radius > 0
        soft = looks.brighten & blurred
        box = _constant("box", SOFT_BOX, torch.int64, device).index_select(0, radius)
        grow = (box - 1) * soft
        inner = torch.add(side, radius, alpha=2)
        full = torch.add(inner, grow, alpha=2)
        # grid side with the border, P (full + 1) + 1 (phases P > 1: no blur)
        fine = torch.addcmul(phases, phases, full).add_(1)
        block = fine * fine
        first = starts(block)
        # One float64 buffer: every stamp in its bordered place, then, for the stamps to blur,
        # their rows before the blur, one per row of ``width`` values: 2 r zeros, the row, 2 r
        # zeros (so that every box of the blur lies inside it): the sampled pixels go straight
        # where they belong, and a row's prefix sums are the cumulative sum of its values.
        rows = side * blurred
        rows_first = starts(rows)
        # stamps brightened without a blur (a defocus radius that rounds to 0 on a coarse grid)
        bright = looks.brighten & ~blurred
        # (the sizes and flags the host needs, read at once)
        size, row_count, blurs, softs, brights, width = torch.cat((
            torch.stack((block, rows, blurred, soft, bright)).sum(1),
            torch.add(side, radius, alpha=4).max().view(1))).tolist() \
            if looks.count else [0] * 6
        width = width + 1 if blurs else 1
        # the brightened, blurred stamps are blurred onto canvases of similar sides (after the
        # rows), brightened and softened there, then copied to their places
        blur_end = size + row_count * width
        canvases = _canvases(torch.nonzero(soft).squeeze(1), full, blur_end, chunk_elements) \
            if softs else None
        work = torch.zeros(blur_end + (canvases.size if canvases else 0), dtype=torch.float64,
                           device=device)
        # pixel (y, x) of entry e goes to ``place[e] + y * pitch[e] + x``; an unblurred stamp's
        # pixel (0, 0) is at its bordered pixel (1, 1) (it does not grow)
        top = first + full + 3
        place = torch.where(blurred, torch.add(rows_first * width, radius, alpha=2)
                            .add_(size + 1), top)
        pitch = (full + 2).masked_fill_(blurred, width)
        images = [b.image for b in books]
        coef = _coefficients(looks, books, lib_of, footprint, side, level, dtype)
        (_sample if chunk_elements >= RAGGED_CHUNK else _sample_per_factor)(
            coef, images, lib_of, side, sub, place, pitch, work, bright if brights else None,
            chunk_elements, phases == 1)
        (_sample_phases if chunk_elements >= RAGGED_CHUNK else _sample_phases_per_side)(
            coef, images, lib_of, side, phases, first, work, chunk_elements)
        if blurs:
            members = torch.nonzero(blurred).squeeze(1)
            # each row divided by its disc's taps (the blur's normalisation, linear), then
            # summed up
            rows_of = torch.repeat_interleave(disc_counts(radius.index_select(0, members)),
                                              side.index_select(0, members))
            prefix = work[size:blur_end].view(-1, width).div_(rows_of[:, None]).cumsum_(1) \
                .view(-1)
            # blurred pixel (0, 0): at the bordered pixel (1, 1), or on the softening canvas at
            # (b − 1, b − 1)
            origin, out_pitch = top, full + 2
            if canvases is not None:
                grown = grow.index_select(0, canvases.members)
                origin = origin.index_copy(0, canvases.members, torch.addcmul(
                    canvases.origin + grown, grown, canvases.side))
                out_pitch = out_pitch.index_copy(0, canvases.members, canvases.side)
            _blur(prefix, members, side, radius, rows_first, width, origin, out_pitch, work,
                  chunk_elements)
        if canvases is not None:
            _soften(work, canvases, top, inner, box, full, chunk_elements)
        # softened stamps are smooth over the box: blur samples may lie (b - 1) / 2 of their
        # grid's pixels apart; the others one pixel (both times the grid's factor)
        gap = torch.where(soft, _constant("gaps", GAPS, torch.float64, device)
                          .index_select(0, radius), _constant("one", 1.0, torch.float64, device)) \
            * _constant("factors", FACTORS, torch.float64, device).index_select(0, coarse)
    return StampSet(pixels=work[:size].to(dtype), first=first, side=full, coarse=coarse,
                    phases=phases, gap=gap)


def _coefficients(looks: Looks, books: Sequence[Atlas], lib_of: Optional[torch.Tensor],
                  footprint, side, level, dtype) -> torch.Tensor:
    """Per entry, how a sample at (gx, gy) pixels from the stamp's centre reads its library's
    atlas (``lib_of`` (E,): the entry's index into ``books``; None: one library).
    Shape: (8, E), rows bx, by, ax, cx, ay, cy, ρ² and the stamp's pixel 0 from its centre
    (one row per number: a chunk's entries gather them with one ``index_select``)."""
    # A sample at (gx, gy) pixels from the stamp's centre reads the atlas at the
    # normalised position (bx + ax gx + cx gy, by + ay gx + cy gy): the template at
    # Rot(−rotation) (gx, gy) in units of half the footprint (so image offset = Rot(rotation) ·
    # template offset), grid_sample's pixel convention (align_corners=False). It is inside the
    # disc when gx² + gy² <= (footprint / 2)² (1 + RIM_MARGIN).
    device = footprint.device
    if lib_of is None:
        book = books[0]
        height, width = book.image.shape[-2:]
        res = book.res.index_select(0, level)
        x0 = book.x0.index_select(0, looks.template)
        y0 = book.y0.view(-1).index_select(0, torch.add(level, looks.template,
                                                        alpha=book.y0.shape[1]))
        size = _constant(f"atlas_size{width},{height}", [[width], [height]], torch.float64,
                         device)
        # (the third row divided by −height: −(x / height), the negation exact)
        turn_size = _constant(f"atlas_turn{width},{height}",
                              [[width], [width], [-height], [height]], torch.float64, device)
    else:
        # every library's tables one after the other (levels padded to the most any has)
        levels = max(int(b.res.numel()) for b in books)
        offsets = list(itertools.accumulate([0] + [int(b.x0.numel()) for b in books[:-1]]))
        template = looks.template + torch.tensor(offsets, device=device).index_select(0, lib_of)
        x0 = torch.cat([b.x0 for b in books]).index_select(0, template)
        y0 = torch.cat([F.pad(b.y0, (0, levels - b.y0.shape[1])) for b in books]).view(-1) \
            .index_select(0, template * levels + level)
        res = torch.stack([F.pad(b.res, (0, levels - b.res.numel())) for b in books]).view(-1) \
            .index_select(0, lib_of * levels + level)
        widths = [float(b.image.shape[-1]) for b in books]
        heights = [float(b.image.shape[-2]) for b in books]
        size = torch.tensor([widths, heights], dtype=torch.float64,
                            device=device).index_select(1, lib_of)
        turn_size = torch.tensor([widths, widths, [-h for h in heights], heights],
                                 dtype=torch.float64, device=device).index_select(1, lib_of)
    scale = res / footprint
    cos, sin = torch.cos(looks.rotation), torch.sin(looks.rotation)
    # (2 x0 + res) / width − 1 and (2 y0 + res) / height − 1; 2 scale cos / width,
    # 2 scale sin / width, 2 scale sin / −height and 2 scale cos / height
    origin = (torch.stack((x0, y0)) * 2 + res) / size - 1
    turn = torch.stack((cos, sin)) * (2 * scale)
    turn = torch.cat((turn, turn.flip(0))) / turn_size
    rim = torch.stack(((footprint / 2) ** 2 * (1.0 + RIM_MARGIN),
                       _constant("centre", CENTRES, torch.float64, device).index_select(0, side)))
    return torch.cat((origin, turn, rim)).to(dtype)


def _read(images: Sequence[torch.Tensor], grid: torch.Tensor,
          lib: Optional[torch.Tensor]) -> torch.Tensor:
    """Bilinear reads of the atlases at ``grid`` (n, 2) normalised positions, each in its
    library's atlas ``images[lib]`` (``lib`` (n,); None: the one library). Shape: -> (n,)."""
    n = grid.shape[0]
    if lib is None:
        return F.grid_sample(images[0], grid.view(1, 1, n, 2), mode="bilinear",
                             padding_mode="zeros", align_corners=False).view(n)
    value = grid.new_zeros(n)
    for k, image in enumerate(images):
        at = torch.nonzero(lib == k).squeeze(1)
        if at.numel():
            value.index_copy_(0, at, F.grid_sample(
                image, grid.index_select(0, at).view(1, 1, -1, 2), mode="bilinear",
                padding_mode="zeros", align_corners=False).view(-1))
    return value


def _sample(coef: torch.Tensor, images: Sequence[torch.Tensor], lib_of: Optional[torch.Tensor],
            side, sub, place, pitch, work: torch.Tensor, bright: Optional[torch.Tensor],
            chunk: int, whole: torch.Tensor) -> None:
    """The stamps sampled at whole pixels (``whole`` (E,): one phase), before their blur,
    written to ``work`` (pixel (y, x) of entry e at ``place[e] + y pitch[e] + x``): each pixel
    the mean of its ``sub x sub`` bilinear samples of the template's mip level at the rotated and
    scaled position, zero outside the footprint's disc; brightened where ``bright`` (E,) says
    so.

    Every stamp is a run of its pixels' samples (pixels row-major), each pixel's ``sub²``
    samples one after the other (row-major in the pixel: sample ``j`` at
    ``(j // sub, j % sub)``), whatever the supersampling: one ``grid_sample`` per chunk of
    runs (a stamp larger than a chunk is a chunk of its own: with a GPU's 2^25 elements, a
    stamp over 5792 pixels wide on its grid), then each pixel's samples summed pairwise, halves
    first (:func:`_pixel_sums`), and divided by ``sub²``."""
    if side.numel() == 0 or not bool(whole.any()):
        return
    device, dtype = coef.device, coef.dtype
    # one item per stamp: its entry, side, supersampling, where its pixel (0, 0) goes in
    # ``work`` and its pitch there (a sample's pixel and row follow from its index)
    order = torch.nonzero(whole).squeeze(1)
    table = torch.stack((side, sub, place, pitch)).index_select(1, order)
    span = (side * sub).index_select(0, order)                    # samples per stamp row
    for item, local in runs(span * span, chunk):
        e = order.index_select(0, item)
        size, factor, at, step = table.index_select(1, item).unbind(0)
        count = factor * factor
        pixel = torch.div(local, count, rounding_mode="floor")
        j = torch.addcmul(local, pixel, count, value=-1)
        row = torch.div(pixel, size, rounding_mode="floor")
        col = torch.addcmul(pixel, row, size, value=-1)
        at = torch.addcmul(at, row, step)
        # the sample's offset in its pixel along x and y (:func:`_sample_offsets`), added to
        # its pixel's position from the stamp's centre
        off = _sample_offsets(dtype, device).index_select(1, torch.add(j, factor, alpha=16))
        bx, by, ax, cx, ay, cy, rho2, centre = coef.index_select(1, e).unbind(0)
        gx, gy = ((torch.stack((col, row)).to(dtype) + centre) + off).unbind(0)
        n = int(local.numel())
        grid = torch.empty(n, 2, dtype=dtype, device=device)
        grid_x, grid_y = grid.unbind(-1)
        torch.addcmul(torch.addcmul(bx, ax, gx), cx, gy, out=grid_x)
        torch.addcmul(torch.addcmul(by, ay, gx), cy, gy, out=grid_y)
        inside = torch.addcmul(gx * gx, gy, gy) <= rho2
        value = _read(images, grid, None if lib_of is None else lib_of.index_select(0, e)) \
            * inside
        value = _pixel_sums(value, factor)
        pixel = torch.nonzero(j == 0).squeeze(1)      # each pixel's first sample
        e, target, count = torch.stack((e, at + col, count)).index_select(1, pixel)
        value = value.index_select(0, pixel) / count.to(dtype)
        if bright is not None:      # (only the pixels of the stamps it brightens)
            which = torch.nonzero(bright.index_select(0, e)).squeeze(1)
            value.index_copy_(0, which, defocus_brighten(value.index_select(0, which)))
        work.index_copy_(0, target, value.to(torch.float64))


def _sample_per_factor(coef: torch.Tensor, images: Sequence[torch.Tensor],
                       lib_of: Optional[torch.Tensor], side, sub, place, pitch,
                       work: torch.Tensor, bright: Optional[torch.Tensor], chunk: int,
                       whole: torch.Tensor) -> None:
    """:func:`_sample` for small chunks (the CPU's), the same bytes: one group per
    supersampling, each pixel's samples broadcast from its numbers rather than gathered per
    sample (less memory traffic, more operations).

    The stamps sampled at whole pixels (``whole`` (E,): one phase), before their blur,
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
    row_of = torch.repeat_interleave(s, output_size=rows)          # each row's index in order
    row_entry = order.index_select(0, row_of)
    row_y = torch.arange(rows, device=device) - (ends - s).index_select(0, row_of)
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
            bx, by, ax, cx, ay, cy, rho2, centre = coef.index_select(1, e)
            gx = (col.to(dtype) + centre) + offsets             # (sub columns, n)
            gy = (row.to(dtype) + centre) + row_offsets         # (sub rows, 1, n)
            n = gx.shape[-1]
            grid = torch.empty(factor, factor, n, 2, dtype=dtype, device=device)
            grid_x, grid_y = grid.unbind(-1)
            torch.addcmul(torch.addcmul(bx, ax, gx), cx, gy, out=grid_x)
            torch.addcmul(torch.addcmul(by, ay, gx), cy, gy, out=grid_y)
            inside = torch.addcmul(gx * gx, gy, gy) <= rho2
            lib = None if lib_of is None else lib_of.index_select(0, e).repeat(factor * factor)
            value = _read(images, grid.view(-1, 2), lib).view(inside.shape) * inside
            while value.numel() > n:         # pairwise, in a fixed order: the same bits anywhere
                value = value.view(2, -1, n).sum(0)
            value = value.view(-1)
            if factor > 1:
                value = value / (factor * factor)
            if bright is not None:      # (only the pixels of the stamps it brightens)
                which = torch.nonzero(bright.index_select(0, e)).squeeze(1)
                value.index_copy_(0, which, defocus_brighten(value.index_select(0, which)))
            work.index_copy_(0, row_at.index_select(0, item) + col, value.to(torch.float64))


def _sample_offsets(dtype, device) -> torch.Tensor:
    """Where sample j of a pixel supersampled ``sub x sub`` lies in the pixel, along x and y,
    at column ``16 sub + j``: ``(b + 0.5) / sub − 0.5`` for its column ``b = j % sub`` and its
    row ``a = j // sub``. Shape: (2, 80)."""
    table = [[0.0] * 80, [0.0] * 80]
    for sub in (1, 2, 4):
        for j in range(sub * sub):
            table[0][16 * sub + j] = (j % sub + 0.5) / sub - 0.5
            table[1][16 * sub + j] = (j // sub + 0.5) / sub - 0.5
    return _constant("sample_offsets", table, dtype, device)


def _pixel_sums(value: torch.Tensor, factor: torch.Tensor) -> torch.Tensor:
    """Each pixel's ``sub²`` samples (one after the other, ``factor`` sub per sample, 4, 2 or
    1) summed pairwise, halves first: sample j plus sample j + sub² / 2, then again, until one
    is left, at the pixel's first sample (the order of a sum over halves: the same bits
    anywhere). Shape: (n,) -> (n,), meaningful at each pixel's first sample."""
    samples = value
    # zeros past the end once: each step's sums reach ``shift`` further and are one shorter by
    # it, their tail still zeros (the same sums as cutting to n and padding again every step)
    value = F.pad(value, (0, 15))
    quad = F.pad(factor == 4, (0, 15))
    for shift in (8, 4, 2, 1):
        first = value[:-shift]
        summed = first + value[shift:]
        value = torch.where(quad[:summed.shape[0]], summed, first) if shift > 2 else summed
    return torch.where(factor > 1, value, samples)


def _sample_phases(coef: torch.Tensor, images: Sequence[torch.Tensor],
                   lib_of: Optional[torch.Tensor], side, phases, first, work: torch.Tensor,
                   chunk: int) -> None:
    """The phase stamps (``phases`` P > 1), written to their bordered places in ``work``: the
    value at ``(y, x) / P`` pixels on the grid around the centre is the mean of the template over
    the pixel square centred there (``P x P`` bilinear samples of the mip level at every 1 / P
    pixel, zero outside the footprint's disc), i.e. the pixel-integrated template at every
    1 / P of a pixel.

    Every phase stamp, whatever its side s, is a run of ``m x m`` samples (``m = P (s + 2)`` per
    axis, centred on the particle, row-major), all read with one ``grid_sample`` per chunk of
    runs, then averaged over every ``P x P`` window (:func:`_window_mean`): the ``n x n`` windows
    starting in the run's first ``n = P (s + 1) + 1`` rows and columns are exactly the entry's
    bordered grid, copied to its place."""
    if side.numel() == 0:
        return
    dtype, device = coef.dtype, coef.device
    members = torch.nonzero(phases > 1).squeeze(1)
    if members.numel() == 0:
        return
    factor = phases.index_select(0, members)
    m = factor * (side.index_select(0, members) + 2)
    # per member: m, 1 − m, 2 P, P² (the sample offsets' and the mean's divisors), its first, n
    per_member = torch.stack((m, PHASE_M * m, factor * factor, first.index_select(0, members),
                              m - factor + 1))
    quad = factor == 4
    member_coef = coef.index_select(1, members)
    member_lib = None if lib_of is None else lib_of.index_select(0, members)
    for e, local in runs(m * m, chunk):
        me, row, p2, at0, ne = per_member.index_select(1, e).unbind(0)
        y = torch.div(local, me, rounding_mode="floor")
        yx = torch.stack((torch.addcmul(local, y, me, value=-1), y))
        # sample offsets from the centre, pixels, along x and along y (:func:`_phase_offsets`)
        gx, gy = _phase_offsets(dtype, device).index_select(0, (yx + row).view(-1)) \
            .view(2, -1).unbind(0)
        bx, by, ax, cx, ay, cy, rho2, _ = member_coef.index_select(1, e).unbind(0)
        count = int(local.numel())
        grid = torch.empty(count, 2, dtype=dtype, device=device)
        grid_x, grid_y = grid.unbind(-1)
        torch.addcmul(torch.addcmul(bx, ax, gx), cx, gy, out=grid_x)
        torch.addcmul(torch.addcmul(by, ay, gx), cy, gy, out=grid_y)
        value = _read(images, grid, None if member_lib is None else member_lib.index_select(0, e))
        value.mul_(torch.addcmul(gx * gx, gy, gy) <= rho2)
        value = _window_mean(value, me, quad.index_select(0, e), p2.to(dtype))
        keep = torch.nonzero((yx < ne).all(0)).squeeze(1)
        col, row = yx.unbind(0)
        at = torch.addcmul(at0 + col, row, ne)
        work.index_copy_(0, at.index_select(0, keep),
                         value.index_select(0, keep).to(torch.float64))


#: Rows of :func:`_phase_offsets`: every m = P (s + 2) of a phase stamp is below it.
PHASE_M = 32


def _phase_offsets(dtype, device) -> torch.Tensor:
    """The offset from the stamp's centre, pixels, of sample b (along x or y) of a phase stamp
    sampled ``m x m`` times, at ``PHASE_M m + b``: ``(b − (m − 1) / 2) / P`` (P = 4 for
    m = 4 (s + 2), s = 3, 5; 2 for s = 7, 9). Shape: (PHASE_M², )."""
    table = [0.0] * (PHASE_M * PHASE_M)
    for s, factor in PHASE_FACTORS.items():
        m = factor * (s + 2)
        for b in range(m):
            table[PHASE_M * m + b] = (b - (m - 1) / 2) / factor
    return _constant("phase_offsets", table, dtype, device)


def _window_mean(value: torch.Tensor, pitch: torch.Tensor, quad: torch.Tensor,
                 divisor: torch.Tensor) -> torch.Tensor:
    """The mean of every ``P x P`` window (stride 1) of runs of ``m x m`` samples laid out one
    after the other, row-major (``pitch`` m per element, P = 4 where ``quad``, else 2), summed
    separably and pairwise (columns, then rows: windows of 2, then, for P = 4, of 4 as two
    adjacent windows of 2), divided by ``divisor`` P² (a power of two: exact). Each window's mean
    is the same arithmetic on its own 16 (or 4) inputs wherever it lies; windows reaching past
    their run's last row or column hold other values (not used).
    Shape: value, pitch, quad (K,) -> (K,)."""
    count = int(value.numel())
    value = F.pad(value, (0, 3))
    value = value[:-1] + value[1:]
    value = torch.where(quad, value[:count] + value[2:count + 2], value[:count])
    # along the columns: each window's value one and two rows down (last element where none)
    down = torch.arange(count, device=value.device) + pitch
    down = torch.stack((down, down + pitch)).clamp_(max=count - 1)
    one, two = down.unbind(0)
    value = value + value.index_select(0, one)
    value = torch.where(quad, value + value.index_select(0, two), value)
    return value / divisor


def _sample_phases_per_side(coef: torch.Tensor, images: Sequence[torch.Tensor],
                            lib_of: Optional[torch.Tensor], side, phases, first,
                            work: torch.Tensor, chunk: int) -> None:
    """:func:`_sample_phases` for small chunks (the CPU's), the same bytes: per side rather than
    in one ragged pass (dense arrays whose coordinates are broadcast from each stamp's numbers
    rather than gathered per sample: less memory traffic, more operations).

    The phase stamps (``phases`` P > 1), written to their bordered places in ``work``: the
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
        c = coef.index_select(1, members)[:, :, None, None]
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
            bx, by, ax, cx, ay, cy, rho2, _ = c[:, lo:lo + per].unbind(0)
            count = bx.shape[0]
            grid = torch.empty(count, m, m, 2, dtype=dtype, device=device)
            grid_x, grid_y = grid.unbind(-1)
            torch.addcmul(torch.addcmul(bx, ax, gx), cx, gy, out=grid_x)
            torch.addcmul(torch.addcmul(by, ay, gx), cy, gy, out=grid_y)
            lib = None if lib_of is None else \
                lib_of.index_select(0, members[lo:lo + per]).repeat_interleave(m * m)
            value = _read(images, grid.view(-1, 2), lib).view(count, m, m)
            value.mul_(torch.addcmul(gx * gx, gy, gy) <= rho2)
            value = _dense_window_mean(value, factor)                           # (count, n, n)
            at = first.index_select(0, members[lo:lo + per])[:, None] + steps
            work.index_copy_(0, at.view(-1), value.reshape(-1).to(torch.float64))


def _dense_window_mean(value: torch.Tensor, factor: int) -> torch.Tensor:
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


def _blur(prefix, members, side, radius, rows_first, width, origin, pitch, work,
          chunk: int) -> None:
    """Disc-blurred stamps ``members`` from their rows' prefix sums (already divided by the
    disc's taps) into ``work``: blurred pixel (Y, X) of entry e at ``origin[e] + Y pitch[e] +
    X`` (its bordered place, or its softening canvas).

    The blurred pixel (Y, X) of a stamp of side s and radius r sums, over the disc's rows
    ``a`` in [−r, r] of half-width ``w = floor(sqrt(r² − a²))``, the stamp's row
    ``y = Y − r − a`` between columns ``X − r − w`` and ``X − r + w``. So every (entry, stamp row
    y, disc row a) is a *segment* that adds box sums of row y (differences of its prefix sums;
    the row's 2 r zeros on either side hold every box) to the ``s + 2 w`` columns of output row
    ``y + r + a`` it reaches, from column ``r − w`` on.
    """
    s, r = side.index_select(0, members), radius.index_select(0, members)
    taps = 2 * r + 1
    item, local = next(runs(s * taps, 1 << 62))                 # the segments, all at once
    rr, ss, tt, row_first, at0, pp = torch.stack(
        (r, s, taps, rows_first.index_select(0, members), origin.index_select(0, members),
         pitch.index_select(0, members))).index_select(1, item)
    # (integers: every formula below is exact, fused where one operation does it)
    y = torch.div(local, tt, rounding_mode="floor")
    j = torch.addcmul(local, y, tt, value=-1)                    # a + r: the disc row from 0
    a = j - rr
    w = _constant("isqrt", ISQRT, torch.int64, local.device).index_select(
        0, torch.addcmul(rr * rr, a, a, value=-1))
    base = torch.add((row_first + y) * width, rr, alpha=2)
    # output pixel (Y, X) of row Y = y + r + a from column X = r − w on
    at = torch.addcmul(at0, y + j, pp) + (rr - w)
    # element x of a segment: the box over the row's columns x − 2 w .. x
    # (rows of a stacked table: gathering them is several times faster than along a second axis)
    consts = torch.stack((base + 1, torch.sub(base, w, alpha=2), at), 1)
    for seg, x in runs(ss + 2 * w, chunk):
        c_hi, c_lo, c_out = consts.index_select(0, seg).add_(x[:, None]).t()
        work.index_add_(0, c_out, prefix.index_select(0, c_hi) - prefix.index_select(0, c_lo))


#: A softening group's canvases hold at most this many times its stamps' own pixels (or at
#: most ``chunk`` values).
SOFTEN_WASTE = 1.5


@dataclass
class _Canvases:
    """Where the brightened, blurred stamps are softened (:func:`_soften`): per group of
    similar sides (:func:`_soften_groups`) its members, canvas side F and the position of its
    ``(M, F, F)`` canvases in ``work``; per member (``members``, the groups' one after the
    other) its canvas's pixel (0, 0) (``origin``) and side (``side``)."""

    groups: list
    members: torch.Tensor
    origin: torch.Tensor
    side: torch.Tensor
    size: int


def _canvases(members, full, base: int, chunk: int) -> _Canvases:
    """The softening canvases of stamps ``members`` (``full`` wide when softened), in ``work``
    from ``base`` on."""
    sides = full.index_select(0, members)
    order = torch.argsort(sides, descending=True, stable=True)
    members = members.index_select(0, order)
    sorted_sides = sides.index_select(0, order).tolist()
    groups, origin, side, at = [], [], [], base
    for lo, hi in _soften_groups(sorted_sides, chunk):
        f = sorted_sides[lo]
        groups.append((members[lo:hi], f, at))
        origin.append(torch.arange(at, at + (hi - lo) * f * f, f * f, device=members.device))
        side.append(members.new_full((hi - lo,), f))
        at += (hi - lo) * f * f
    return _Canvases(groups=groups, members=members,
                     origin=origin[0] if len(origin) == 1 else torch.cat(origin),
                     side=side[0] if len(side) == 1 else torch.cat(side), size=at - base)


def _soften(work, canvases: _Canvases, top, inner, box, full, chunk: int) -> None:
    """Brighten and soften the stamps of ``canvases``, each disc-blurred on its canvas (its
    ``n x n`` stamp, n = ``inner``, at offset ``b − 1``, b = ``box``), into their bordered
    ``(full + 2)²`` blocks: the whole ``full x full`` (``full = n + 2 (b − 1)``) is the
    brightened stamp convolved with a normalised, centred ``b x b`` box twice
    (:func:`soft_box`).

    The stamps go in groups of similar sides (:func:`_soften_groups`: largest first, each group's
    canvases at most ``chunk`` values or at most 1.5 times its stamps' own pixels), so that the
    work stays proportional to the stamps' pixels, not to the count times the largest. A group's
    canvases are one zero-filled dense float64 array ``(M, F, F)`` (F the group's largest
    ``full``), brightened (whole with a GPU's chunks: zeros stay zero; the stamps' own pixels
    with the CPU's); each of the four box passes
    (rows, rows, columns, columns) takes cumulative sums along its axis (per row or column: its
    sums do not depend on the other stamps, nor on F or the padding, which only add leading or
    trailing exact zeros) and differences them at the stamp's own half-width h:
    ``out[x] = S[x + h] − S[x − h − 1]`` (divided by ``b⁴`` at the end). The boxes reach at
    most ``b − 1`` beyond the stamp, so they stay inside its canvas; where a span is all zeros
    the difference is exactly zero.
    """
    base = canvases.groups[0][2]
    if chunk >= RAGGED_CHUNK:
        # (:func:`defocus_brighten` in place: the same operations on the same numbers)
        work[base:base + canvases.size].mul_(2).clamp_(min=0).log_().div_(3).exp_() \
            .clamp_(max=1)
    else:       # (small chunks: only the stamps' own pixels, less arithmetic)
        n = inner.index_select(0, canvases.members)
        grown = box.index_select(0, canvases.members) - 1
        at = torch.addcmul(canvases.origin + grown, grown, canvases.side)
        for e, local in runs(n * n, chunk):
            ne = n.index_select(0, e)
            row = torch.div(local, ne, rounding_mode="floor")
            pixel = torch.addcmul(at.index_select(0, e) + local - row * ne, row,
                                  canvases.side.index_select(0, e))
            work.index_copy_(0, pixel, defocus_brighten(work.index_select(0, pixel)))
    for members, side, at in canvases.groups:
        _soften_group(work, members, side, at, top, box, full, chunk)


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


def _soften_group(work, members, side: int, at: int, top, box, full, chunk: int) -> None:
    """One group of :func:`_soften`: ``members`` on canvases ``side`` wide from ``at`` on, into
    their places from their bordered pixel (1, 1) ``top`` on."""
    m = int(members.numel())
    b = box.index_select(0, members)
    f = full.index_select(0, members)
    top = top.index_select(0, members)
    dense = work[at:at + m * side * side].view(m, side, side)
    half = (b - 1) // 2
    pad = int(half.max()) + 1
    # out[x] = S[hi] − S[lo] in the padded sums: hi = x + pad + h, lo = hi − b
    hi = torch.arange(pad, pad + side, device=work.device) + half.view(m, 1)
    ends = torch.stack((hi, hi - b.view(m, 1)))                         # (2, m, side)
    ends = {2: ends.view(2, m, 1, side).expand(2, m, side, side).unbind(0),
            1: ends.view(2, m, side, 1).expand(2, m, side, side).unbind(0)}
    for axis in (2, 2, 1, 1):
        sums = F.pad(dense, (pad, pad, 0, 0) if axis == 2 else (0, 0, pad, pad)).cumsum_(axis)
        hi_a, lo_a = ends[axis]
        dense = sums.gather(axis, hi_a) - sums.gather(axis, lo_a)
    # the four boxes' 1 / b
    dense = dense / _constant("box4", BOX4, torch.float64, work.device).index_select(0, b) \
        .view(m, 1, 1)
    flat = dense.reshape(-1)
    for e, local in runs(f * f, chunk):
        fe = f.index_select(0, e)
        y = torch.div(local, fe, rounding_mode="floor")
        x = torch.addcmul(local, y, fe, value=-1)
        work.index_copy_(0, torch.addcmul(top.index_select(0, e) + x, y, fe + 2),
                         flat.index_select(0, torch.add(x, torch.add(y, e, alpha=side),
                                                        alpha=side)))
