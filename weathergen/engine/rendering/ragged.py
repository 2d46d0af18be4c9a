"""Ragged layouts: items of different sizes laid out as flat runs of one long tensor.

Every stage of the render core works on such runs (a stamp's pixels, a blur row's columns, a
patch's pixel blocks), so that a call costs a bounded number of tensor operations whatever the
number and sizes of the particles; :func:`runs` splits a layout into chunks of bounded memory
(:func:`spans` says where, also for a layout given as runs of equal items).
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
    larger than that is a chunk of its own), as :func:`chunk_spans` says. Yields, per chunk,
    ``(item (m,), local (m,))``: each element's item index and its index inside the item's run,
    in layout order; with ``spans``, ``(item, local, (a, b))``, the chunk holding items
    ``a .. b − 1`` (whole or in part).
    """
    count = int(sizes.numel())
    if count == 0:
        return
    ends = torch.cumsum(sizes, 0)
    pieces = chunk_spans(sizes, limit, groups, split, ends=(None, ends))
    begins = ends - sizes
    device = sizes.device
    for a, b, lo, hi in pieces:
        # (repeats alone: each item's index, one operation; the items a..b then shifted by a)
        if a == 0 and b == count:
            item = torch.repeat_interleave(sizes, output_size=hi - lo)
        else:
            item = torch.repeat_interleave(sizes[a:b], output_size=hi - lo)
            if a:
                item.add_(a)
        local = torch.arange(lo, hi, device=device) - begins[item]
        yield (item, local, (a, b)) if spans else (item, local)


def chunk_spans(sizes: torch.Tensor, limit: int, groups: Optional[torch.Tensor] = None,
                split: Optional[int] = None, repeats: Optional[torch.Tensor] = None,
                ends: Optional[tuple] = None) -> list:
    """Where :func:`runs` cuts items with ``sizes`` elements each: ``(a, b, lo, hi)`` per chunk
    (items ``a .. b − 1``, elements ``lo .. hi − 1``), in layout order, chunks without elements
    left out. Chunks hold about ``limit`` elements, cut between items (an item larger than
    that is a chunk of its own).

    ``groups`` (n,) int64, non-decreasing: a group of more than ``split`` elements (default
    ``limit``) is cut into chunks of its own before the item holding each multiple of ``split``
    of its own elements, counted from the group's first element; smaller groups are never split,
    and are packed whole into chunks of up to ``limit`` elements. So how a group's elements are
    chunked depends neither on the groups around it nor on ``limit`` (the render core relies on
    this to make a pair's pixels independent of the batch it is in and of the chunk size).

    ``repeats`` (n,) int64: the layout given as runs of equal items, entry ``k`` standing for
    ``repeats[k]`` items of ``sizes[k]`` elements in group ``groups[k]`` (item indices count
    those items), so that a layout of many equal items needs no tensor per item; ``ends``: the
    cumulative sums of ``repeats`` (None without ``repeats``) and of ``sizes * repeats``,
    where the caller has them.
    Two host synchronisations at most.
    """
    n = int(sizes.numel())
    if n == 0:
        return []
    if ends is not None:
        item_ends, ends = ends
    elif repeats is not None:
        item_ends, ends = torch.cumsum(repeats, 0), torch.cumsum(sizes * repeats, 0)
    else:
        item_ends, ends = None, torch.cumsum(sizes, 0)
    split = limit if groups is None or split is None else split
    b, t = _group_bounds(n, groups, item_ends, ends)
    pieces, large = _packed(b, t, limit, split)
    if large:
        cuts = iter(_cuts(sizes, repeats, item_ends, ends, large, split))
        pieces = [p for piece in pieces for p in ([piece] if piece is not None else next(cuts))]
    return [p for p in pieces if p[3] > p[2]]


def _group_bounds(n: int, groups: Optional[torch.Tensor], item_ends: Optional[torch.Tensor],
                  ends: torch.Tensor) -> tuple[list, list]:
    """Where each group of :func:`chunk_spans`'s ``n`` entries starts, as its first item and its
    first element, then where the layout ends (without ``groups``: one group). ``item_ends``,
    ``ends``: the cumulative items (None: one per entry) and elements. One host
    synchronisation. Shape: -> two lists of G + 1 ints."""
    if groups is None:
        if item_ends is None:
            return [0, n], [0, ends[-1:].tolist()[0]]
        b, t = [[0, total] for total in torch.stack((item_ends[-1], ends[-1])).tolist()]
        return b, t
    first = torch.searchsorted(groups, groups.unique_consecutive())
    bounds = torch.cat((first, first.new_full((1,), n)))
    zero = ends.new_zeros(1)
    b, t = torch.stack((bounds if item_ends is None else torch.cat((zero, item_ends))[bounds],
                        torch.cat((zero, ends))[bounds])).tolist()
    return b, t


def _packed(b: list, t: list, limit: int, split: int) -> tuple[list, list]:
    """Groups (first items ``b``, first elements ``t``, see :func:`_group_bounds`) packed into
    chunks ``(a, b, lo, hi)`` of up to ``limit`` elements, in order, empty groups left out; a
    group of more than ``split`` elements is a ``None`` in that list, to be cut by
    :func:`_cuts`, and is listed in the second list as ``(a, b, lo, hi)``."""
    pieces, open_piece, large = [], None, []
    for g in range(len(b) - 1):
        size = t[g + 1] - t[g]
        if size == 0:
            continue
        if size > split:
            if open_piece is not None:
                pieces.append(open_piece)
                open_piece = None
            pieces.append(None)                             # (cut below)
            large.append((b[g], b[g + 1], t[g], t[g + 1]))
        elif open_piece is not None and open_piece[3] - open_piece[2] + size <= limit:
            open_piece = (open_piece[0], b[g + 1], open_piece[2], t[g + 1])
        else:
            if open_piece is not None:
                pieces.append(open_piece)
            open_piece = (b[g], b[g + 1], t[g], t[g + 1])
    if open_piece is not None:
        pieces.append(open_piece)
    return pieces, large


def _cuts(sizes, repeats, item_ends, ends, large: list, split: int) -> list:
    """The chunks of each large group ``(a, b, lo, hi)`` (items ``a .. b − 1``, elements
    ``lo .. hi − 1``): a cut before the item holding each element ``lo + k split`` (not before
    item ``a``), as a list of chunks per group. One host synchronisation."""
    device = sizes.device
    marks, owner = [], []
    for g, (a, b, lo, hi) in enumerate(large):
        if b - a > 1:
            marks.append(torch.arange(lo + split, hi, split, device=device))
            owner.append(torch.full_like(marks[-1], g))
    found = [[], [], []]
    if marks:
        mark, group = torch.cat(marks), torch.cat(owner)
        spans = torch.tensor(large, device=device)
        # the item holding each mark (its run, then its place in the run), kept inside
        # a + 1 .. b − 1, and where it starts
        run = torch.searchsorted(ends, mark, right=True)
        if repeats is None:
            item = run
        else:
            run_start = ends[run] - sizes[run] * repeats[run]
            item = item_ends[run] - repeats[run] + torch.div(mark - run_start, sizes[run],
                                                             rounding_mode="floor")
        item = torch.minimum(torch.maximum(item, spans[group, 0] + 1), spans[group, 1] - 1)
        if repeats is None:
            begin = ends[item - 1]
        else:
            run = torch.searchsorted(item_ends, item, right=True)
            begin = ends[run] - sizes[run] * (item_ends[run] - item)
        found = torch.stack((group, item, begin)).tolist()
    out = [[] for _ in large]
    last = [None] * len(large)
    for g, item, begin in zip(*found):
        if item != last[g]:
            out[g].append((item, begin))
            last[g] = item
    result = []
    for (a, b, lo, hi), inner in zip(large, out):
        cut = [(a, lo)] + inner + [(b, hi)]
        result.append([(cut[i][0], cut[i + 1][0], cut[i][1], cut[i + 1][1])
                       for i in range(len(cut) - 1)])
    return result
