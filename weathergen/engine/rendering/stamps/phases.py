"""Phase stamps: small stamps sampled at every 1 / P pixel, each value the template averaged
over the pixel square centred there (see the package doc)."""

from __future__ import annotations

from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..ragged import runs
from .tables import PHASE_FACTORS, constant
from .atlas import read_samples


def sample_phases(coef: torch.Tensor, images: Sequence[torch.Tensor],
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
        value = read_samples(images, grid, None if member_lib is None else member_lib.index_select(0, e))
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
    return constant("phase_offsets", table, dtype, device)


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


def sample_phases_per_side(coef: torch.Tensor, images: Sequence[torch.Tensor],
                            lib_of: Optional[torch.Tensor], side, phases, first,
                            work: torch.Tensor, chunk: int) -> None:
    """:func:`sample_phases` for small chunks (the CPU's), the same bytes: per side rather than
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
        gx = constant(f"gx{factor},{m}", [[[(b - (m - 1) / 2) / factor for b in range(m)]]],
                       dtype, device)
        gy = constant(f"gy{factor},{m}", [[[(b - (m - 1) / 2) / factor] for b in range(m)]],
                       dtype, device)
        steps = constant(f"steps{n}", list(range(n * n)), torch.int64, device)
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
            value = read_samples(images, grid.view(-1, 2), lib).view(count, m, m)
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
