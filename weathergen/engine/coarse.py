"""Coarse grids across depth edges: large billboards drawn coarse, occluded per image pixel.

Large billboards (fog) are splatted on a grid ``f`` times coarser than the image and upsampled
bilinearly (:mod:`~weathergen.engine.stamps`, :mod:`~weathergen.engine.composite`). Their light
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
import torch.nn.functional as F

#: The ramp of one billboard is this fraction of one rank wide (< 1 / 2: a step between ranks).
SINGLE_SPREAD = 0.25
SQRT3 = math.sqrt(3.0)


def footprint_depths(depth: torch.Tensor, factor: int, height: int, width: int
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """The nearest and the farthest scene depth of every coarse pixel's footprint: the image
    pixels its bilinear upsampling reaches, ``f j − f / 2 .. f j + 3 f / 2 − 1`` per axis (the
    image's edge replicated). Shape: (V, 1, H, W) -> two (V, 1, h, w), h = ceil(H / f)."""
    half = factor // 2
    pad = (half, half + (-width % factor), half, half + (-height % factor))
    d = F.pad(depth, pad, mode="replicate")
    far = F.max_pool2d(d, 2 * factor, factor)
    near = -F.max_pool2d(-d, 2 * factor, factor)
    return near, far


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
        return (at - self.start[group]) / self.count[group].clamp(min=1)

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
    ``near``) plus, at every image pixel next to an ambiguous coarse pixel, the ambiguous light
    in front of it (see the module doc). Shape: base (C, V, H, W); near, far (C, V, h, w);
    moments four (V, h, w) -> (C, V, H, W). Differentiable in base, near, far and moments."""
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
    y0, y1, wy = _neighbours(height, h, factor, device)
    x0, x1, wx = _neighbours(width, w, factor, device)
    rows = ambiguous.index_select(1, y0) | ambiguous.index_select(1, y1)     # (V, H, w)
    touched = rows.index_select(2, x0) | rows.index_select(2, x1)           # (V, H, W)
    v, y, x = torch.nonzero(touched, as_tuple=True)
    rank = order.in_front(group.view(-1).index_select(0, v), info.depth[v, y, x])
    flat_delta = delta.reshape(channels, -1)
    lo, width_ = lo.reshape(-1), (hi - lo).reshape(-1)
    total = None
    for cy, wgt_y in ((y0, 1 - wy), (y1, wy)):
        for cx, wgt_x in ((x0, 1 - wx), (x1, wx)):
            j = (v * h + cy.index_select(0, y)) * w + cx.index_select(0, x)
            weight = (wgt_y.index_select(0, y) * wgt_x.index_select(0, x)).to(base.dtype)
            share = _share(rank, lo.index_select(0, j), width_.index_select(0, j), base.dtype)
            term = flat_delta.index_select(1, j) * (weight * share)
            total = term if total is None else total + term
    pixel = (v * height + y) * width + x
    return base.reshape(channels, -1).index_add(1, pixel, total).view(channels, views, height,
                                                                      width)


def _share(rank: torch.Tensor, lo: torch.Tensor, width: torch.Tensor, dtype) -> torch.Tensor:
    """``clamp((P − a) / (b − a), 0, 1)``; a step at ``a`` where the ramp has no width."""
    rank = rank.to(dtype)
    flat = width <= 0
    ramp = ((rank - lo) / torch.where(flat, torch.ones_like(width), width)).clamp(0, 1)
    return torch.where(flat, (rank > lo).to(dtype), ramp)


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
