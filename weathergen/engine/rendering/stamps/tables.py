"""Stamp tables: the constants every stage of stamp building reads (sides, grid levels, disc
taps, softening boxes) and each entry's stamp layout from its footprint (:func:`stamp_geometry`)."""

from __future__ import annotations

import math
from typing import Optional, Union

import torch



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
    steps = constant("side_steps", SIDE_STEPS, torch.float64, footprint.device)
    at = torch.searchsorted(steps, footprint / 2 + 0.5, right=True)
    side, sub = constant("sides", SIDE_TABLE, torch.int64, footprint.device) \
        .index_select(1, at).unbind(0)
    # (the template's resolution over the footprint as ``int / tensor`` computes it: times the
    # reciprocal)
    level = floor_log2((footprint * sub).reciprocal() * resolution)
    level = level.clamp(0, level_count - 1) if isinstance(level_count, int) \
        else torch.minimum(level.clamp(min=0), level_count - 1)
    phases = sub.masked_fill(radius > 0, 1)
    return footprint, radius, coarse, side, sub, level, phases


#: ``−((s − 1) // 2)`` for every stamp side s (a stamp's pixel 0 from its centre).
CENTRES = [float(-((s - 1) // 2)) for s in range(int(SIDES[-1]) + 1)]


#: Taps of the disc of radius r (integer offsets with dx² + dy² <= r²) for r = 0 .. 255 (the
#: defocus radii a record can store).
DISC_TAPS = [sum(2 * math.isqrt(r * r - a * a) + 1 for a in range(-r, r + 1)) for r in range(256)]


_CONSTANTS: dict = {}


def constant(name: str, values, dtype, device) -> torch.Tensor:
    """A small constant tensor, made once per dtype and device."""
    key = (name, dtype, str(device))
    if key not in _CONSTANTS:
        _CONSTANTS[key] = torch.tensor(values, dtype=dtype, device=device)
    return _CONSTANTS[key]


def disc_counts(radius: torch.Tensor) -> torch.Tensor:
    """Taps of the disc of each radius r (integer offsets with dx² + dy² <= r²).
    Shape: (n,) int64 -> (n,) float64."""
    return constant("taps", DISC_TAPS, torch.float64, radius.device).index_select(0, radius)


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


#: The box of a stamp made as the research code makes it (``stamp_style = "research"``), for
#: every radius: none (a box of one pixel); the research code does not soften a brightened
#: stamp (docs/render.md, "The look of the paper's presets").
RESEARCH_BOX = 1


#: A softened stamp's blur-sample gap per radius, ``(b − 1) · GAP_SHARE`` grid pixels (a
#: research stamp keeps its record's samples, whatever its box), and each grid level's factor
#: ``2**L`` (image pixels per grid pixel).
GAPS = [(b - 1) * GAP_SHARE for b in SOFT_BOX]


FACTORS = [2.0 ** level for level in range(COARSE_MAX_LEVEL + 1)]


#: ``floor(sqrt(d))`` for d = 0 .. 255² (the half-widths of the disc's rows).
ISQRT = [math.isqrt(d) for d in range(255 * 255 + 1)]


#: Per box width b: ``b⁴`` (the four box passes' normalisation).
BOX4 = [float(b) ** 4 for b in range(2 * (255 // 4 + 2) + 2)]
