"""Ragged layouts: where :func:`~weathergen.engine.rendering.ragged.runs` and
:func:`~weathergen.engine.rendering.ragged.chunk_spans` cut a layout into chunks."""

from __future__ import annotations

import random

import torch

from weathergen.engine.rendering.ragged import chunk_spans, runs


def cut_by_hand(sizes, limit, groups=None, split=None):
    """The documented rule, item by item in plain Python: ``(a, b, lo, hi)`` per chunk."""
    ends = [0]
    for s in sizes:
        ends.append(ends[-1] + s)
    keys = groups if groups is not None else [0] * len(sizes)
    split = limit if groups is None or split is None else split
    bounds = [i for i in range(len(sizes)) if i == 0 or keys[i] != keys[i - 1]] + [len(sizes)]
    pieces, open_piece = [], None
    for a, b in zip(bounds, bounds[1:]):
        lo, hi = ends[a], ends[b]
        if hi == lo:
            continue
        if hi - lo > split:
            if open_piece:
                pieces.append(open_piece)
                open_piece = None
            cuts = [a]
            for mark in range(lo + split, hi, split):       # before the item holding the mark
                item = min(max(next(i for i in range(a, b) if ends[i + 1] > mark), a + 1), b - 1)
                if item != cuts[-1] and b - a > 1:
                    cuts.append(item)
            cuts.append(b)
            pieces += [(x, y, ends[x], ends[y]) for x, y in zip(cuts, cuts[1:])]
        elif open_piece and open_piece[3] - open_piece[2] + hi - lo <= limit:
            open_piece = (open_piece[0], b, open_piece[2], hi)
        else:
            if open_piece:
                pieces.append(open_piece)
            open_piece = (a, b, lo, hi)
    if open_piece:
        pieces.append(open_piece)
    return [p for p in pieces if p[3] > p[2]]


def test_a_layout_is_cut_before_the_items_holding_each_multiple_of_the_limit():
    """By hand: items of 3, 5, 2, 7 elements in chunks of 6: elements 6 and 12 lie in items 1
    and 3; the same layout as runs of equal items (2, 2, 2, 3, 3 as three 2s and two 3s)."""
    assert chunk_spans(torch.tensor([3, 5, 2, 7]), 6) == [(0, 1, 0, 3), (1, 3, 3, 10),
                                                          (3, 4, 10, 17)]
    assert chunk_spans(torch.tensor([2, 3]), 5, repeats=torch.tensor([3, 2])) == [
        (0, 2, 0, 4), (2, 4, 4, 9), (4, 5, 9, 12)]
    # groups: the first (8 elements) is cut at 4 of its own, the next two packed whole
    assert chunk_spans(torch.tensor([3, 5, 2, 2]), 6, torch.tensor([0, 0, 1, 2]), 4) == [
        (0, 1, 0, 3), (1, 2, 3, 8), (2, 4, 8, 12)]


def test_chunks_follow_the_rule_for_items_one_by_one_or_as_runs_of_equal_items():
    """Random layouts (empty items and runs included): the chunks of the items one by one
    (and the item and place of each element that runs yields) and of the same items given as
    runs of equal items are those of the rule written out by hand."""
    rng = random.Random(0)
    for _ in range(400):
        n = rng.randint(1, 12)
        repeats = [rng.choice([0, 1, 1, 2, 3, 5]) for _ in range(n)]
        sizes = [rng.choice([0, 1, 2, 3, 4, 7, 20]) for _ in range(n)]
        groups = sorted(rng.randint(0, 4) for _ in range(n))
        limit, split = rng.choice([1, 2, 3, 5, 8, 16, 100]), rng.choice([None, 1, 3, 7, 50])
        flat = [s for s, r in zip(sizes, repeats) for _ in range(r)]
        flat_groups = [g for g, r in zip(groups, repeats) for _ in range(r)]
        if not flat:
            continue
        for grouped in (False, True):
            g = torch.tensor(groups) if grouped else None
            fg = torch.tensor(flat_groups) if grouped else None
            expected = cut_by_hand(flat, limit, flat_groups if grouped else None, split)
            assert chunk_spans(torch.tensor(flat), limit, fg, split) == expected
            assert chunk_spans(torch.tensor(sizes), limit, g, split,
                               repeats=torch.tensor(repeats)) == expected
            starts = [sum(flat[:i]) for i in range(len(flat))]
            got = [(a, b, item.tolist(), local.tolist())
                   for item, local, (a, b) in runs(torch.tensor(flat), limit, fg, split,
                                                   spans=True)]
            want = []
            for a, b, lo, hi in expected:
                item = [i for i in range(a, b) for _ in range(flat[i])]
                want.append((a, b, item, [e - starts[i] for e, i in zip(range(lo, hi), item)]))
            assert got == want
