"""Stamp sampling: the mip atlas of every template and the reads of each stamp's samples from it
(pixel-centred stamps; phase stamps: :mod:`.phases`; see the package doc)."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..ragged import runs
from ...weather.templates import TemplateLibrary
from ..tracks import Looks
from .tables import CENTRES, RIM_MARGIN, constant
from .filters import defocus_brighten


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


def coefficients(looks: Looks, books: Sequence[Atlas], lib_of: Optional[torch.Tensor],
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
        size = constant(f"atlas_size{width},{height}", [[width], [height]], torch.float64,
                         device)
        # (the third row divided by −height: −(x / height), the negation exact)
        turn_size = constant(f"atlas_turn{width},{height}",
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
                       constant("centre", CENTRES, torch.float64, device).index_select(0, side)))
    return torch.cat((origin, turn, rim)).to(dtype)


def read_samples(images: Sequence[torch.Tensor], grid: torch.Tensor,
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


def sample_stamps(coef: torch.Tensor, images: Sequence[torch.Tensor], lib_of: Optional[torch.Tensor],
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
        value = read_samples(images, grid, None if lib_of is None else lib_of.index_select(0, e)) \
            * inside
        value = _pixel_sums(value, factor)
        pixel = torch.nonzero(j == 0).squeeze(1)      # each pixel's first sample
        e, target, count = torch.stack((e, at + col, count)).index_select(1, pixel)
        value = value.index_select(0, pixel) / count.to(dtype)
        if bright is not None:      # (only the pixels of the stamps it brightens)
            which = torch.nonzero(bright.index_select(0, e)).squeeze(1)
            value.index_copy_(0, which, defocus_brighten(value.index_select(0, which)))
        work.index_copy_(0, target, value.to(torch.float64))


def sample_per_factor(coef: torch.Tensor, images: Sequence[torch.Tensor],
                       lib_of: Optional[torch.Tensor], side, sub, place, pitch,
                       work: torch.Tensor, bright: Optional[torch.Tensor], chunk: int,
                       whole: torch.Tensor) -> None:
    """:func:`sample_stamps` for small chunks (the CPU's), the same bytes: one group per
    supersampling, each pixel's samples broadcast from its numbers rather than gathered per
    sample (less memory traffic, more operations).

    The stamps sampled at whole pixels (``whole`` (E,): one phase), before their blur,
    written to ``work`` (pixel (y, x) of entry e at ``place[e] + y pitch[e] + x``): each pixel
    the mean of its ``sub x sub`` bilinear samples of the template's mip level at the rotated and
    scaled position, zero outside the footprint's disc; brightened where ``bright`` (E,) says
    so."""
    if side.numel() == 0 or not bool(whole.any()):
        return
    rows = _StampRows.of(side, sub, place, pitch, whole)
    for g, factor in enumerate(rows.factors):
        lo, hi = rows.cuts[g], rows.cuts[g + 1]
        for item, col in runs(rows.size[lo:hi], max(1, chunk // (factor * factor))):
            if lo:
                item = item + lo
            e = rows.entry.index_select(0, item)
            value = _pixel_means(coef, images, lib_of, e, rows.y.index_select(0, item), col,
                                 factor)
            if bright is not None:      # (only the pixels of the stamps it brightens)
                which = torch.nonzero(bright.index_select(0, e)).squeeze(1)
                value.index_copy_(0, which, defocus_brighten(value.index_select(0, which)))
            work.index_copy_(0, rows.at.index_select(0, item) + col, value.to(torch.float64))


@dataclass
class _StampRows:
    """The rows of the stamps :func:`sample_per_factor` samples: entries by supersampling factor
    (``factors``, of 4, 2, 1 those present), one item per stamp row, the groups' rows one after
    the other (group g's are rows ``cuts[g] .. cuts[g + 1] − 1``). Per row (R,) int64: its
    ``entry``, its row ``y`` in the stamp, its ``size`` (the stamp's side) and where its pixel 0
    goes in ``work`` (``at``; a pixel's column is then its index in the row)."""

    factors: list
    cuts: list
    entry: torch.Tensor
    y: torch.Tensor
    size: torch.Tensor
    at: torch.Tensor

    @classmethod
    def of(cls, side, sub, place, pitch, whole) -> "_StampRows":
        """The rows of the entries ``whole`` says, laid out as ``place`` and ``pitch`` say
        (see :func:`sample_per_factor`). Shape: (E,) each."""
        device = side.device
        groups = [(f, torch.nonzero((sub == f) & whole).squeeze(1)) for f in (4, 2, 1)]
        groups = [(f, m) for f, m in groups if m.numel()]
        order = torch.cat([m for _, m in groups]) if len(groups) > 1 else groups[0][1]
        s = side.index_select(0, order)
        ends = torch.cumsum(s, 0)
        last = list(itertools.accumulate(int(m.numel()) for _, m in groups))
        cuts = [0] + ends.index_select(0, torch.tensor(last, device=device) - 1).tolist()
        rows = cuts[-1]
        row_of = torch.repeat_interleave(s, output_size=rows)      # each row's index in order
        entry = order.index_select(0, row_of)
        y = torch.arange(rows, device=device) - (ends - s).index_select(0, row_of)
        size, row_place, row_pitch = torch.stack((side, place, pitch)).index_select(1, entry)
        return cls([f for f, _ in groups], cuts, entry, y, size,
                   torch.addcmul(row_place, y, row_pitch))


def _pixel_means(coef: torch.Tensor, images: Sequence[torch.Tensor],
                 lib_of: Optional[torch.Tensor], e: torch.Tensor, row: torch.Tensor,
                 col: torch.Tensor, factor: int) -> torch.Tensor:
    """Pixels (``row``, ``col``) of the stamps of entries ``e`` supersampled ``factor x
    factor``: the mean of their samples, zero outside the footprint's disc (see
    :func:`sample_per_factor`). Shape: (n,) each -> (n,)."""
    dtype, device = coef.dtype, coef.device
    # sample offsets in a pixel along one axis: (sub, 1); a pixel's sub² samples are
    # row-major, (sub rows, sub columns), so a sample's x depends on its column alone and its
    # y on its row: the coordinates are computed per axis (sub, n) and broadcast
    offsets = constant(f"offsets{factor}", [[(k + 0.5) / factor - 0.5]
                                             for k in range(factor)], dtype, device)
    row_offsets = constant(f"row_offsets{factor}", [[[(k + 0.5) / factor - 0.5]]
                                                     for k in range(factor)], dtype, device)
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
    value = read_samples(images, grid.view(-1, 2), lib).view(inside.shape) * inside
    while value.numel() > n:         # pairwise, in a fixed order: the same bits anywhere
        value = value.view(2, -1, n).sum(0)
    value = value.view(-1)
    if factor > 1:
        value = value / (factor * factor)
    return value


def _sample_offsets(dtype, device) -> torch.Tensor:
    """Where sample j of a pixel supersampled ``sub x sub`` lies in the pixel, along x and y,
    at column ``16 sub + j``: ``(b + 0.5) / sub − 0.5`` for its column ``b = j % sub`` and its
    row ``a = j // sub``. Shape: (2, 80)."""
    table = [[0.0] * 80, [0.0] * 80]
    for sub in (1, 2, 4):
        for j in range(sub * sub):
            table[0][16 * sub + j] = (j % sub + 0.5) / sub - 0.5
            table[1][16 * sub + j] = (j // sub + 0.5) / sub - 0.5
    return constant("sample_offsets", table, dtype, device)


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
