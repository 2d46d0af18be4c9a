"""Stamp filters: the defocus disc blur, the brightening of blurred stamps and their softening by
normalised boxes (see the package doc)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..ragged import runs
from .tables import BOX4, ISQRT, RAGGED_CHUNK, constant


def defocus_brighten(blurred: torch.Tensor) -> torch.Tensor:
    """The depth-of-field alpha of a disc-blurred template: ``min(1, (2 b)^(1/3))``.

    The blur spreads a particle's alpha thin; doubling it and taking the cube root brings it
    back up (near, out-of-focus particles look like large soft discs rather than vanishing),
    as the paper's research code does. Shape: any -> same.
    """
    return torch.exp(torch.log((2 * blurred).clamp(min=0)) / 3).clamp(max=1)


def disc_blur(prefix, members, side, radius, rows_first, width, origin, pitch, work,
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
    w = constant("isqrt", ISQRT, torch.int64, local.device).index_select(
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
    """Where the brightened, blurred stamps are softened (:func:`soften`): per group of
    similar sides (:func:`_soften_groups`) its members, canvas side F and the position of its
    ``(M, F, F)`` canvases in ``work``; per member (``members``, the groups' one after the
    other) its canvas's pixel (0, 0) (``origin``) and side (``side``)."""

    groups: list
    members: torch.Tensor
    origin: torch.Tensor
    side: torch.Tensor
    size: int


def soften_canvases(members, full, base: int, chunk: int) -> _Canvases:
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


def soften(work, canvases: _Canvases, top, inner, box, full, chunk: int) -> None:
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
    """One group of :func:`soften`: ``members`` on canvases ``side`` wide from ``at`` on, into
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
    dense = dense / constant("box4", BOX4, torch.float64, work.device).index_select(0, b) \
        .view(m, 1, 1)
    flat = dense.reshape(-1)
    for e, local in runs(f * f, chunk):
        fe = f.index_select(0, e)
        y = torch.div(local, fe, rounding_mode="floor")
        x = torch.addcmul(local, y, fe, value=-1)
        work.index_copy_(0, torch.addcmul(top.index_select(0, e) + x, y, fe + 2),
                         flat.index_select(0, torch.add(x, torch.add(y, e, alpha=side),
                                                        alpha=side)))
