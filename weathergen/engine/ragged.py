"""Ragged layouts: items of different sizes laid out as flat runs of one long tensor.

Every stage of the render core works on such runs (a stamp's pixels, a blur row's columns, a
patch's pixel blocks), so that a call costs a bounded number of tensor operations whatever the
number and sizes of the particles; :func:`runs` splits a layout into chunks of bounded memory.
"""

from __future__ import annotations

from typing import Iterator, Optional

import torch


def starts(sizes: torch.Tensor) -> torch.Tensor:
    """Where each item's run begins. Shape: (n,) int64 -> (n,) int64."""
    return torch.cumsum(sizes, 0) - sizes


def runs(sizes: torch.Tensor, limit: int, groups: Optional[torch.Tensor] = None,
         split: Optional[int] = None, spans: bool = False) -> Iterator[tuple]:
    """Split items with ``sizes`` elements each into chunks of about ``limit`` elements (an item
    larger than that is a chunk of its own). Yields, per chunk, ``(item (m,), local (m,))``: each
    element's item index and its index inside the item's run, in layout order; with ``spans``,
    ``(item, local, (a, b))``, the chunk holding items ``a .. b − 1`` (whole or in part).

    ``groups`` (n,) int64, non-decreasing: a group of more than ``split`` elements (default
    ``limit``) is cut into chunks of its own where its own elements reach multiples of
    ``split``, counted from the group's first element; smaller groups are never split, and are
    packed whole into chunks of up to ``limit`` elements. So how a group's elements are chunked
    depends neither on the groups around it nor on ``limit`` (the render core relies on this to
    make a pair's pixels independent of the batch it is in and of the chunk size).
    One host synchronisation for the whole layout (three when it is split into chunks).
    """
    count = int(sizes.numel())
    if count == 0:
        return
    ends = torch.cumsum(sizes, 0)
    if groups is None:
        pieces = _cuts(ends, 0, count, 0, limit)
    else:
        split = limit if split is None else split
        first = torch.searchsorted(groups, groups.unique_consecutive())
        bounds = torch.cat((first, first.new_full((1,), count)))
        totals = torch.cat((ends.new_zeros(1), ends))[bounds]
        pieces, open_piece = [], None
        b, t = bounds.tolist(), totals.tolist()
        for g in range(len(b) - 1):
            size = t[g + 1] - t[g]
            if size == 0:
                continue
            if size > split:
                if open_piece is not None:
                    pieces.append(open_piece)
                    open_piece = None
                pieces.extend(_cuts(ends, b[g], b[g + 1], t[g], split))
            elif open_piece is not None and open_piece[3] - open_piece[2] + size <= limit:
                open_piece = (open_piece[0], b[g + 1], open_piece[2], t[g + 1])
            else:
                if open_piece is not None:
                    pieces.append(open_piece)
                open_piece = (b[g], b[g + 1], t[g], t[g + 1])
        if open_piece is not None:
            pieces.append(open_piece)
    begins = ends - sizes
    device = sizes.device
    for a, b, lo, hi in pieces:
        if hi == lo:
            continue
        # (repeats alone: each item's index, one operation; the items a..b then shifted by a)
        if a == 0 and b == count:
            item = torch.repeat_interleave(sizes, output_size=hi - lo)
        else:
            item = torch.repeat_interleave(sizes[a:b], output_size=hi - lo)
            if a:
                item.add_(a)
        local = torch.arange(lo, hi, device=device) - begins[item]
        yield (item, local, (a, b)) if spans else (item, local)


def _cuts(ends: torch.Tensor, a: int, b: int, offset: int, limit: int) -> list:
    """Chunks ``(first item, end item, first element, end element)`` of items ``a..b`` whose
    elements start at ``offset``, cut at multiples of ``limit`` counted from ``offset``."""
    total = ends[b - 1:b].tolist()[0] if b > a else offset      # (one read of the host)
    if total - offset <= limit or b - a == 1:
        return [(a, b, offset, total)]
    marks = torch.arange(offset + limit, total, limit, device=ends.device)
    inner = torch.searchsorted(ends[a:b], marks, right=True) + a
    inner = torch.unique(inner.clamp(a + 1, b - 1))
    cut = [a] + inner.tolist() + [b]
    bounds = [offset] + ends[torch.tensor(cut[1:], device=ends.device) - 1].tolist()
    return [(cut[i], cut[i + 1], bounds[i], bounds[i + 1]) for i in range(len(cut) - 1)]
