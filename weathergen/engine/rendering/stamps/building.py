"""Stamp building: :class:`StampSet` and :func:`build` / :func:`build_many`, which lay out every
entry's stamp and run the sampling and filters over them (see the package doc)."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any, Optional, Sequence

import torch
import torch.nn.functional as F

from ....errors import ConfigError
from ..ragged import starts
from ...weather.templates import TemplateLibrary
from ..tracks import Looks
from .phases import sample_phases, sample_phases_per_side
from .atlas import atlas, coefficients, sample_per_factor, sample_stamps
from .tables import (COARSE_SIDE, FACTORS, GAPS, RAGGED_CHUNK, RESEARCH_BOX, SOFT_BOX,
                     STAMP_CHUNK_ELEMENTS, constant, disc_counts, stamp_geometry)
from .filters import disc_blur, soften, soften_canvases


@dataclass
class StampSet:
    """The stamps of E entries, ragged: entry e's stamp, ``side x side`` pixels with a one-pixel
    zero border around it, sampled every ``1 / P`` pixel (P = ``phases[e]``): the stamp's
    value at ``(y, x) / P − (side + 1) / 2`` pixels from the particle's centre (row, column of
    the ``n x n`` grid, ``n = P (side + 1) + 1``; its outer rows and columns are the zero
    border) is at ``pixels[first[e] + y n + x]``. With P = 1 that is the stamp's pixels with
    their border.

    ``gap``: how far apart (image pixels) an entry's blur samples may lie along its streak
    without a visible ripple (:func:`~weathergen.engine.rendering.tracks.streak_samples`): ``(b − 1) / 2``
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
    that stored them draws it (:func:`~weathergen.engine.rendering.tracks.streak_samples`).
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
    libs, which = _distinct_libraries(parts)
    if len(libs) > 1 and chunk_elements < RAGGED_CHUNK:
        runs_of_one = [[part for part, _ in group]
                       for _, group in itertools.groupby(zip(parts, which), key=lambda pw: pw[1])]
        if len(runs_of_one) > 1:
            return StampSet.cat([build_many(run, dtype=dtype, coarse_side=coarse_side,
                                            chunk_elements=chunk_elements)
                                 for run in runs_of_one])
    looks = parts[0][0] if len(parts) == 1 else Looks.cat([p[0] for p in parts])
    device = looks.template.device
    _check_template_indices(parts)
    with torch.no_grad():
        books = [atlas(lib, dtype, device) for lib in libs]
        lib_of, resolution, level_count = _entry_libraries(parts, libs, which, books, device)
        layout = _Layout.of(looks, resolution, level_count, coarse_side, chunk_elements)
        canvases = layout.canvases
        work = torch.zeros(layout.blur_end + (canvases.size if canvases else 0),
                           dtype=torch.float64, device=device)
        _sample(layout, looks, books, lib_of, work, dtype, chunk_elements)
        if layout.blurs:
            _blur(layout, work, chunk_elements)
        if canvases is not None:
            soften(work, canvases, layout.top, layout.inner, layout.box, layout.full,
                   chunk_elements)
        gap = layout.gaps()
        if looks.research is not None:      # the record's own blur samples, as the research code
            gap = gap.masked_fill(looks.research, math.inf)
    return StampSet(pixels=work[:layout.size].to(dtype), first=layout.first, side=layout.full,
                    coarse=layout.coarse, phases=layout.phases, gap=gap)


def _distinct_libraries(parts: Sequence[tuple[Looks, TemplateLibrary]]
                        ) -> tuple[list[TemplateLibrary], list[int]]:
    """The parts' libraries, each once (the same object, or the same digest and name), and
    which of them each part draws with."""
    libs: list[TemplateLibrary] = []
    which = []
    for _, lib in parts:
        k = next((i for i, known in enumerate(libs)
                  if known is lib or (known.digest, known.name) == (lib.digest, lib.name)), None)
        if k is None:
            libs.append(lib)
            k = len(libs) - 1
        which.append(k)
    return libs, which


def _check_template_indices(parts: Sequence[tuple[Looks, TemplateLibrary]]) -> None:
    """Raise ConfigError when a part's template index lies outside its library."""
    for (part, lib) in parts:
        low, high = [t.tolist() for t in torch.aminmax(part.template)] if part.count \
            else (0, 0)
        if not 0 <= low <= high < lib.count:
            raise ConfigError(f"particle template index out of range for the {lib.count} "
                              f"templates of '{lib.name}'")


def _entry_libraries(parts, libs: list, which: list, books: list, device) -> tuple:
    """Each entry's library: ``(lib_of, resolution, level_count)``, with one library ``(None,
    its side, its mip levels)``, else per entry (E,) the library's index (int64), its side
    (float64) and its atlas's mip levels (int64)."""
    if len(libs) == 1:
        return None, libs[0].resolution, int(books[0].res.numel())
    lib_of = torch.repeat_interleave(torch.tensor(which, device=device),
                                     torch.tensor([p[0].count for p in parts], device=device))
    resolution, level_count = torch.tensor(
        [[float(lib.resolution) for lib in libs], [b.res.numel() for b in books]],
        dtype=torch.float64, device=device).index_select(1, lib_of).unbind(0)
    return lib_of, resolution, level_count.long()


@dataclass
class _Layout:
    """Where every entry's stamp goes in one float64 work buffer: every stamp in its bordered
    place (``first``, the entry's ``P (full + 1) + 1`` squared values), then, for the stamps to
    blur, their rows before the blur (from ``rows_first`` on, one per row of ``width`` values:
    2 r zeros, the row, 2 r zeros, so that every box of the blur lies inside it), then the
    softening canvases. Per entry (E,): ``footprint`` (float64), ``radius``, ``coarse``,
    ``side``, ``sub``, ``level``, ``phases`` as :func:`stamp_geometry` gives them; ``blurred``,
    ``soft`` (blurred and brightened: softened afterwards) and ``bright`` (brightened without a
    blur) bool; the softening ``box``, by how much softening grows the stamp on each side
    (``grow``), its side after the blur (``inner``) and after softening (``full``), int64; where
    its bordered pixel (1, 1) is (``top``); pixel (y, x) of its samples goes to ``place + y pitch
    + x``. On the host: the stamps' values ``size``, the blur rows' end ``blur_end``, how many
    stamps are blurred, softened and brightened unblurred (``blurs``, ``softs``, ``brights``);
    the softening ``canvases`` (:func:`soften_canvases`; None without).
    """

    footprint: torch.Tensor
    radius: torch.Tensor
    coarse: torch.Tensor
    side: torch.Tensor
    sub: torch.Tensor
    level: torch.Tensor
    phases: torch.Tensor
    blurred: torch.Tensor
    soft: torch.Tensor
    bright: torch.Tensor
    box: torch.Tensor
    grow: torch.Tensor
    inner: torch.Tensor
    full: torch.Tensor
    first: torch.Tensor
    rows_first: torch.Tensor
    top: torch.Tensor
    place: torch.Tensor
    pitch: torch.Tensor
    size: int
    width: int
    blur_end: int
    blurs: int
    softs: int
    brights: int
    canvases: Optional[Any]

    @classmethod
    def of(cls, looks: Looks, resolution, level_count, coarse_side: Optional[int],
           chunk_elements: int) -> "_Layout":
        """The layout of the entries of ``looks`` (``resolution``, ``level_count``: see
        :func:`stamp_geometry`)."""
        device = looks.template.device
        footprint, radius, coarse, side, sub, level, phases = stamp_geometry(
            looks.footprint.to(torch.float64), looks.defocus, resolution, level_count,
            coarse_side, looks.coarse)
        # brightened blurred stamps are softened afterwards and grow by the kernel's reach
        blurred = radius > 0
        soft = looks.brighten & blurred
        box = constant("box", SOFT_BOX, torch.int64, device).index_select(0, radius)
        if looks.research is not None:      # (the research code does not soften its stamps)
            box = box.masked_fill(looks.research, RESEARCH_BOX)
        grow = (box - 1) * soft
        inner = torch.add(side, radius, alpha=2)
        full = torch.add(inner, grow, alpha=2)
        # grid side with the border, P (full + 1) + 1 (phases P > 1: no blur)
        fine = torch.addcmul(phases, phases, full).add_(1)
        block = fine * fine
        first = starts(block)
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
        canvases = soften_canvases(torch.nonzero(soft).squeeze(1), full, blur_end,
                                   chunk_elements) if softs else None
        # an unblurred stamp's pixel (0, 0) is at its bordered pixel (1, 1) (it does not grow);
        # a blurred one's samples go to its rows, after their 2 r zeros
        top = first + full + 3
        place = torch.where(blurred, torch.add(rows_first * width, radius, alpha=2)
                            .add_(size + 1), top)
        pitch = (full + 2).masked_fill_(blurred, width)
        return cls(footprint, radius, coarse, side, sub, level, phases, blurred, soft, bright,
                   box, grow, inner, full, first, rows_first, top, place, pitch, size, width,
                   blur_end, blurs, softs, brights, canvases)

    def gaps(self) -> torch.Tensor:
        """How far apart each entry's blur samples may lie (image pixels, see
        :class:`StampSet`). Shape: (E,) float64."""
        # softened stamps are smooth over the box: blur samples may lie (b - 1) / 2 of their
        # grid's pixels apart; the others one pixel (both times the grid's factor)
        device = self.radius.device
        return torch.where(self.soft, constant("gaps", GAPS, torch.float64, device)
                           .index_select(0, self.radius),
                           constant("one", 1.0, torch.float64, device)) \
            * constant("factors", FACTORS, torch.float64, device).index_select(0, self.coarse)


def _sample(layout: _Layout, looks: Looks, books: list, lib_of: Optional[torch.Tensor],
            work: torch.Tensor, dtype: torch.dtype, chunk_elements: int) -> None:
    """Sample every stamp from its template into ``work``: the stamps sampled at whole pixels
    where ``layout.place`` says (see :func:`~.sampling.sample_stamps`), the phase stamps in
    their bordered places (:func:`~.phases.sample_phases`)."""
    images = [b.image for b in books]
    coef = coefficients(looks, books, lib_of, layout.footprint, layout.side, layout.level, dtype)
    ragged = chunk_elements >= RAGGED_CHUNK
    (sample_stamps if ragged else sample_per_factor)(
        coef, images, lib_of, layout.side, layout.sub, layout.place, layout.pitch, work,
        layout.bright if layout.brights else None, chunk_elements, layout.phases == 1)
    (sample_phases if ragged else sample_phases_per_side)(
        coef, images, lib_of, layout.side, layout.phases, layout.first, work, chunk_elements)


def _blur(layout: _Layout, work: torch.Tensor, chunk_elements: int) -> None:
    """Disc-blur the blurred stamps' rows in ``work`` into their bordered places, or onto their
    softening canvases (see the package doc)."""
    members = torch.nonzero(layout.blurred).squeeze(1)
    # each row divided by its disc's taps (the blur's normalisation, linear), then summed up
    rows_of = torch.repeat_interleave(disc_counts(layout.radius.index_select(0, members)),
                                      layout.side.index_select(0, members))
    prefix = work[layout.size:layout.blur_end].view(-1, layout.width) \
        .div_(rows_of[:, None]).cumsum_(1).view(-1)
    # blurred pixel (0, 0): at the bordered pixel (1, 1), or on the softening canvas at
    # (b − 1, b − 1)
    origin, out_pitch = layout.top, layout.full + 2
    canvases = layout.canvases
    if canvases is not None:
        grown = layout.grow.index_select(0, canvases.members)
        origin = origin.index_copy(0, canvases.members, torch.addcmul(
            canvases.origin + grown, grown, canvases.side))
        out_pitch = out_pitch.index_copy(0, canvases.members, canvases.side)
    disc_blur(prefix, members, layout.side, layout.radius, layout.rows_first, layout.width,
              origin, out_pitch, work, chunk_elements)
