"""The splat's output and the grids it is laid out on: :class:`Sums` (the per-pixel sums of a
splat call), :class:`Grids` (where each grid level's planes sit in them), the levels a call's
stamps need (:func:`grids_for`) and the scene depth on each of them (:func:`scene_depths`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from .coarse import CoarseDepths, footprint_depths
from .stamps import COARSE_MAX_LEVEL, StampSet


@dataclass
class Grids:
    """Where the planes of each grid level sit in the flat sums.

    ``levels``: ``(level, offset, h, w, margin)`` per level drawn (coarsest first): P planes of
    ``(h + 1) x (w + 2 margin)`` values from ``offset`` on, plane ``v``'s pixel ``(y, x)`` at
    ``offset + (v (h + 1) + y) (w + 2 margin) + margin + x``; the margins and row ``h`` collect
    what falls outside the image. P is V on the image grid and ``copies`` V on a coarse grid
    (``copies = 2``: planes ``v`` against the nearest depth of each coarse pixel's footprint,
    planes ``V + v`` against the farthest). ``size``: the total; ``views``: V; ``height``,
    ``width``: the image's.
    """

    levels: list
    size: int
    views: int
    height: int
    width: int
    copies: int = 1

    def count(self, level_index: int) -> int:
        """The planes of one level: V, or ``copies`` V on a coarse grid."""
        return self.views * (self.copies if self.levels[level_index][0] else 1)

    def planes(self, values: torch.Tensor, level_index: int) -> torch.Tensor:
        """One level's sums without margins. Shape: (C, N) -> (C, P, h, w) (a view)."""
        _, offset, h, w, m = self.levels[level_index]
        count = self.count(level_index)
        size = count * (h + 1) * (w + 2 * m)
        grid = values[:, offset:offset + size].view(values.shape[0], count, h + 1, w + 2 * m)
        return grid[..., :h, m:m + w]


@dataclass
class Sums:
    """The splat's output. Shape: values (1 + C, N), the sums A, C_r, C_g, C_b (then, where the
    coarse grids are depth-aware, the two moment sums; and, for a layered render, the depth sum
    ``Σ θ B V z``: the instances' last colour channel) laid out as :class:`Grids` says; reached
    (V,) bool, which views any blur sample was splatted into (a view none reached does not
    depend on the particles); coarse: what the depth-aware upsampling needs (None: no coarse
    grid, or ``depth_aware=False``)."""

    values: torch.Tensor
    grids: Grids
    reached: torch.Tensor
    coarse: Optional[CoarseDepths] = None


def grids_for(stamps: StampSet, views: int, height: int, width: int, copies: int = 1) -> Grids:
    """The grid levels the stamps need (the image grid only when a stamp is drawn on it or
    none is coarse), each with a margin as wide as its widest patch, and ``copies`` planes per
    view on a coarse grid. A
    level left out would add exact zeros to every view (sums are never −0), so leaving it out
    changes no bit and saves a full-size plane per view (fog draws on a coarse grid alone). One
    host synchronisation."""
    top = COARSE_MAX_LEVEL + 1
    if stamps.count:
        widest = torch.zeros(top, dtype=torch.long, device=stamps.side.device) \
            .scatter_reduce(0, stamps.coarse, stamps.side + 1, "amax")
        used = torch.stack((torch.bincount(stamps.coarse, minlength=top), widest)).tolist()
    else:
        used = [[0] * top, [0] * top]
    levels, offset = [], 0
    drawn = {c for c, n in enumerate(used[0]) if n}
    for c in sorted(drawn | {0} if not drawn - {0} else drawn, reverse=True):
        f = 2 ** c
        h, w = -(-height // f), -(-width // f)
        m = used[1][c]
        levels.append((c, offset, h, w, m))
        offset += views * (copies if c else 1) * (h + 1) * (w + 2 * m)
    return Grids(levels=levels, size=offset, views=views, height=height, width=width,
                 copies=copies)


def scene_depths(depth: torch.Tensor, grids: Grids, dtype) -> tuple[torch.Tensor, list]:
    """The scene depth on every grid, laid out as the sums (margins and the extra row −∞): on
    a coarse grid with two copies, the nearest then the farthest depth of each coarse pixel's
    footprint (:func:`~weathergen.engine.rendering.coarse.footprint_depths`), with one, the depth averaged
    over f x f blocks (the image's edge replicated up to a whole block). Shape: depth
    (V, 1, H, W) -> (N,), and per level the footprints' (nearest, farthest) (V, h, w) (None
    where not drawn twice)."""
    depth = depth.detach().to(dtype)
    parts, footprints = [], []
    for c, _, _, _, m in grids.levels:
        f = 2 ** c
        d, pair = depth, None
        if c and grids.copies == 2:
            pair = footprint_depths(d, f, grids.height, grids.width)
            d = torch.cat(pair)
            pair = (pair[0][:, 0], pair[1][:, 0])
        elif c:
            pad = (0, -grids.width % f, 0, -grids.height % f)
            d = F.avg_pool2d(F.pad(d, pad, mode="replicate") if any(pad) else d, f)
        parts.append(F.pad(d, (m, m, 0, 1), value=-float("inf")).reshape(-1))
        footprints.append(pair)
    return torch.cat(parts), footprints
