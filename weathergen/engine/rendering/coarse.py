"""Coarse grids across depth edges: large billboards drawn coarse, occluded per image pixel.

Large billboards (fog) are splatted on a grid ``f`` times coarser than the image and upsampled
bilinearly (:mod:`~weathergen.engine.rendering.stamps`, :mod:`~weathergen.engine.rendering.planes`). Their light
is smooth, but the visibility ``V = 1 / (1 + exp(β (z − D)))`` of a billboard at depth ``z`` in
front of the scene depth ``D`` is not: along a depth edge (a near column before a far wall) and
where a billboard cuts a surface it changes from one image pixel to the next. One scene depth per
coarse pixel gives every pixel of its footprint the same visibility, and the upsampling spreads
it over a band of about ``f`` pixels: fog leaks over the near side of an edge, or stops short on
the far side, in steps of ``f`` pixels.

So each coarse pixel ``j`` is splatted twice, against the nearest and the farthest scene depth
of its footprint (the ``2f x 2f`` image pixels its bilinear upsampling reaches:
:func:`footprint_depths`), giving the sums ``S_near`` and ``S_far`` (``A``, the colour sums), and
``ΔS = S_far − S_near`` is the light of the billboards whose visibility changes inside the
footprint (the *ambiguous* ones). Where no coarse pixel is ambiguous the planes are the plain
bilinear upsampling of ``S_near``. An image pixel ``p`` of depth ``D_p`` sees from neighbour
``j`` the light ``S_near + r_j(P(D_p)) ΔS_j``, where

- ``P(D)`` is the fraction of the view's coarse blur samples nearer than ``D`` (their depth rank,
  :class:`DepthOrder`): a step at every billboard's depth, exact where one billboard is ambiguous;
- ``r_j`` is the share of the ambiguous light in front of ``D_p``: a ramp over the ambiguous
  billboards' ranks, their light-weighted mean ``m`` (the sums of ``θ B ΔV φ`` and ``θ B ΔV φ²``,
  ``φ`` a blur sample's rank ``(k + 1/2) / N``, splatted as two more channels) ``± √3 s`` (a uniform
  spread of their standard deviation ``s``, at least ``1 / (4 N)``: one billboard is a step
  between the ranks before and after it), clipped to ``[P(D_near), P(D_far)]``.

The ramp is differentiable in the sums (gradients reach the billboards' positions, depths,
colours and transparencies through ``S_near``, ``S_far`` and the moments); the ranks are a step
function of the depths and pass no gradient. Measured against the exact render (every billboard
pixel splatted) on real pairs, see docs/engine.md, "Large billboards".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

#: The ramp of one billboard is this fraction of one rank wide (< 1 / 2: a step between ranks).
SINGLE_SPREAD = 0.25
SQRT3 = math.sqrt(3.0)


def footprint_depths(depth: torch.Tensor, factor: int, height: int, width: int
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """The nearest and the farthest scene depth of every coarse pixel's footprint: the image
    pixels its bilinear upsampling reaches, ``f j − f / 2 .. f j + 3 f / 2 − 1`` per axis (within
    the image). Shape: (V, 1, H, W) -> two (V, 1, h, w), h = ceil(H / f)."""
    near = _window(_window(depth, factor, 2, torch.amin, torch.minimum), factor, 3, torch.amin,
                   torch.minimum)
    far = _window(_window(depth, factor, 2, torch.amax, torch.maximum), factor, 3, torch.amax,
                  torch.maximum)
    return near, far


def _window(x: torch.Tensor, factor: int, dim: int, reduce, pick) -> torch.Tensor:
    """Along ``dim``: the extremum (``reduce`` over a dimension, ``pick`` of two tensors) over
    ``f j − f / 2 .. f j + 3 f / 2 − 1`` for every coarse index j: of half blocks (each value
    read once), then of four half blocks two apart (half block k holds ``(k − 1) f / 2 ..
    k f / 2 − 1``; those outside the image hold nothing)."""
    half, n = factor // 2, x.shape[dim]
    whole = n // half
    blocks = reduce(x.narrow(dim, 0, whole * half).unflatten(dim, (whole, half)), dim + 1) \
        if half > 1 else x
    if n % half:
        blocks = torch.cat((blocks, reduce(x.narrow(dim, whole * half, n % half), dim,
                                           keepdim=True)), dim)
    coarse = -(-n // factor)
    shape = list(blocks.shape)
    empty = float("inf") if reduce is torch.amin else -float("inf")
    shape[dim] = 1
    head = blocks.new_full(shape, empty)
    shape[dim] = 2 * coarse + 1 - blocks.shape[dim]
    blocks = torch.cat((head, blocks, blocks.new_full(shape, empty)), dim)
    paired = blocks.unflatten(dim, (coarse + 1, 2))
    pairs = pick(paired.select(dim + 1, 0), paired.select(dim + 1, 1))
    return pick(pairs.narrow(dim, 0, coarse), pairs.narrow(dim, 1, coarse))


def _squash(z: torch.Tensor) -> torch.Tensor:
    """A depth >= 0 mapped monotonically into [0, 1] in float64 (``+inf`` to 1)."""
    z = z.to(torch.float64)
    return 1 - torch.reciprocal(1 + z)


@dataclass
class DepthOrder:
    """The depths of the blur samples drawn on coarse grids, sorted per group (a grid level and
    a view: ``group = level V + view``). Shape: keys (N,) float64 ``group + squash(z)`` sorted;
    start, count (G,) int64, where each group's keys begin and how many it holds."""

    keys: torch.Tensor
    start: torch.Tensor
    count: torch.Tensor

    @classmethod
    def of(cls, z: torch.Tensor, group: torch.Tensor, groups: int
           ) -> tuple["DepthOrder", torch.Tensor]:
        """The order of samples at depths ``z`` (N,) in groups ``group`` (N,) int64, and each
        sample's rank ``φ = (k + 1/2) / n`` in its group of n (N,) float64 (no gradient)."""
        keys, order = torch.sort(group.to(torch.float64) + _squash(z.detach()), stable=True)
        count = torch.bincount(group, minlength=groups)
        start = torch.cumsum(count, 0) - count
        g = group.index_select(0, order)
        rank = torch.empty_like(keys)
        position = torch.arange(order.numel(), device=z.device, dtype=torch.float64)
        rank.index_copy_(0, order, (position - start.index_select(0, g) + 0.5)
                         / count.index_select(0, g))
        return cls(keys=keys, start=start, count=count), rank

    def in_front(self, group: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """``P``: the fraction of group ``group``'s samples nearer than ``depth`` (no
        gradient). Shape: (K,) int64 or broadcastable, (K,) -> (K,) float64."""
        group = torch.broadcast_to(group, depth.shape)
        at = torch.searchsorted(self.keys, (group.to(torch.float64) + _squash(depth.detach()))
                                .contiguous())
        return (at - self.start[group]).to(torch.float64) / self.count[group].clamp(min=1)

    def spread(self, group: torch.Tensor) -> torch.Tensor:
        """The half-width in rank of one billboard's ramp, ``SINGLE_SPREAD / n``."""
        return SINGLE_SPREAD / self.count[group].clamp(min=1).to(torch.float64)


@dataclass
class CoarseDepths:
    """What the depth-aware upsampling of the coarse grids needs, from the splat: the scene
    depth (V, H, W); per grid level drawn (as ``Grids.levels``, None for the image grid) the
    nearest and farthest depth of each coarse pixel's footprint (V, h, w); the order of the
    coarse blur samples; where the two moment channels sit in the sums (``moments``: index of
    the first)."""

    depth: torch.Tensor
    footprints: list
    order: DepthOrder
    moments: int


def _neighbours(size: int, coarse: int, factor: int, device
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per image row (or column) the two coarse samples bilinear upsampling mixes and the
    second one's weight, as ``F.interpolate`` computes them (``(x + 0.5) / f − 0.5``, clamped
    to the edges). Shape: -> (size,) int64, (size,) int64, (size,) float64."""
    x = ((torch.arange(size, device=device, dtype=torch.float64) + 0.5) / factor - 0.5).clamp(min=0)
    i0 = torch.floor(x).long().clamp(max=coarse - 1)
    i1 = (i0 + 1).clamp(max=coarse - 1)
    return i0, i1, x - i0


def ramps(near: torch.Tensor, far: torch.Tensor, moments: tuple, bounds: tuple,
          spread: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per coarse pixel: the ambiguous light ``ΔS = S_far − S_near`` and its ramp ``[a, b]`` in
    rank (see the module doc). Shape: near, far (C, V, h, w) the sums against the nearest and
    the farthest depth; moments: the near and far sums of ``θ B V φ`` and ``θ B V φ²`` (V, h, w)
    each; bounds: ``P`` of the footprint's nearest and farthest depth (V, h, w); spread (V, 1, 1)
    -> ΔS (C, V, h, w), a, b (V, h, w)."""
    delta = far - near
    mass = delta[0]
    some = mass > 0
    safe = torch.where(some, mass, torch.ones_like(mass))
    m1 = torch.where(some, (moments[2] - moments[0]) / safe, torch.zeros_like(mass))
    m2 = torch.where(some, (moments[3] - moments[1]) / safe, torch.zeros_like(mass))
    mean = m1.clamp(0, 1)
    sd = torch.sqrt((m2 - mean * mean).clamp(min=0) + (spread * spread).to(mass.dtype))
    lo = torch.maximum(mean - SQRT3 * sd, bounds[0].to(mass.dtype))
    hi = torch.maximum(torch.minimum(mean + SQRT3 * sd, bounds[1].to(mass.dtype)), lo)
    return delta, lo, hi


def across_edges(base: torch.Tensor, near: torch.Tensor, far: torch.Tensor, moments: tuple,
                 info: CoarseDepths, index: int, level: int) -> torch.Tensor:
    """The upsampled planes of one coarse level (``base``: the bilinear upsampling of
    ``near``, added to in place) plus, at every image pixel next to an ambiguous coarse pixel,
    the ambiguous light in front of it (see the module doc). Shape: base (C, V, H, W); near,
    far (C, V, h, w); moments four (V, h, w) -> (C, V, H, W). Differentiable in base, near, far
    and moments."""
    channels, views, height, width = base.shape
    h, w = near.shape[-2:]
    factor = 2 ** level
    ambiguous = (far != near).any(0)                                       # (V, h, w)
    if not bool(ambiguous.any()):
        return base
    device = base.device
    order = info.order
    group = (level * views + torch.arange(views, device=device)).view(views, 1, 1)
    near_d, far_d = info.footprints[index]
    bounds = (order.in_front(group, near_d), order.in_front(group, far_d))
    delta, lo, hi = ramps(near, far, moments, bounds, order.spread(group))
    v, y, x = _pixels_near(ambiguous, height, width, factor)
    pixel = (v * height + y) * width + x
    rank = order.in_front(group.view(-1).index_select(0, v),
                          info.depth.reshape(-1).index_select(0, pixel)).to(base.dtype)
    y0, y1, wy = (t.index_select(0, y) for t in _neighbours(height, h, factor, device))
    x0, x1, wx = (t.index_select(0, x) for t in _neighbours(width, w, factor, device))
    wy, wx = wy.to(base.dtype), wx.to(base.dtype)
    # the four neighbours (rows y0, y1 times columns x0, x1), each with its ramp and light
    row0, row1 = v * h + y0, v * h + y1
    j = torch.stack((row0 * w + x0, row0 * w + x1, row1 * w + x0, row1 * w + x1))
    cells = torch.cat((lo[None], (hi - lo)[None], delta)).reshape(2 + channels, -1)
    near4 = cells.index_select(1, j.view(-1)).view(2 + channels, 4, -1)
    weight = torch.stack(((1 - wy) * (1 - wx), (1 - wy) * wx, wy * (1 - wx), wy * wx))
    terms = near4[2:] * (_share(rank, near4[0], near4[1]) * weight)          # (C, 4, K)
    total = (terms[:, 0] + terms[:, 1]) + (terms[:, 2] + terms[:, 3])
    base.view(channels, -1).index_add_(1, pixel, total)
    return base


def _pixels_near(ambiguous: torch.Tensor, height: int, width: int, factor: int
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The image pixels one of whose four bilinear neighbours is ambiguous, as (view, row,
    column) (K,) each, each once: the pixels of every cell ``(i, j)`` (those whose first
    neighbours are row i and column j) that holds an ambiguous corner."""
    device = ambiguous.device
    cell = ambiguous | torch.cat((ambiguous[:, 1:], ambiguous[:, -1:]), 1)
    cell = cell | torch.cat((cell[:, :, 1:], cell[:, :, -1:]), 2)
    v, i, j = torch.nonzero(cell, as_tuple=True)
    h, w = ambiguous.shape[-2:]
    rows = torch.bincount(_neighbours(height, h, factor, device)[0], minlength=h)
    cols = torch.bincount(_neighbours(width, w, factor, device)[0], minlength=w)
    first_row, first_col = torch.cumsum(rows, 0) - rows, torch.cumsum(cols, 0) - cols
    nr, nc = rows.index_select(0, i), cols.index_select(0, j)
    size = nr * nc
    total = int(size.sum())
    which = torch.repeat_interleave(torch.arange(v.numel(), device=device), size,
                                    output_size=total)
    at = torch.arange(total, device=device) - (torch.cumsum(size, 0) - size).index_select(0, which)
    across = nc.index_select(0, which)
    y = first_row.index_select(0, i).index_select(0, which) + torch.div(at, across,
                                                                       rounding_mode="floor")
    x = first_col.index_select(0, j).index_select(0, which) + torch.remainder(at, across)
    return v.index_select(0, which), y, x


def _share(rank: torch.Tensor, lo: torch.Tensor, span: torch.Tensor) -> torch.Tensor:
    """``clamp((P − a) / (b − a), 0, 1)``; a step at ``a`` where the ramp has no width."""
    flat = span <= 0
    ramp = ((rank - lo) / torch.where(flat, torch.ones_like(span), span)).clamp(0, 1)
    return torch.where(flat, (rank > lo).to(lo.dtype), ramp)


def drop_moments(grid: torch.Tensor, info: CoarseDepths) -> torch.Tensor:
    """A level's planes without the two moment channels. Shape: (C + 2, ...) -> (C, ...)."""
    k = info.moments
    return torch.cat((grid[:k], grid[k + 2:])) if k + 2 < grid.shape[0] else grid[:k]


def moment_channels(colour: torch.Tensor, rank: torch.Tensor, passive: int) -> torch.Tensor:
    """The blur samples' colour channels with ``φ`` and ``φ²`` inserted before the passive
    ones. Shape: (I, C), (I,) -> (I, C + 2)."""
    rank = rank.to(colour.dtype)[:, None]
    active = colour.shape[1] - passive
    parts: Sequence[torch.Tensor] = (colour[:, :active], rank, rank * rank, colour[:, active:])
    return torch.cat(parts, 1)
