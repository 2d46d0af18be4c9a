"""Stage 4 of the render core, first half: the splat's sums on the image grid.

The splat's :class:`Sums` hold, per view, ``A = Σ θ B V`` and
``C_c = Σ γ_c θ B V`` on the image grid and on the coarse grids of large billboards (fog).
:func:`planes` crops every grid's margins (:class:`_Crop`) and brings the coarse grids to the
image grid (bilinear upsampling by an integer factor, :func:`upsample`, coarsest first; across
depth edges where the splat drew them against the footprints' depths), then adds the image grid's
own sums. :class:`LayerPlanes` does the same for combined weather, one layer and frame at a time,
and holds the layers' gradients. What the planes become, the frames and opacities of each blend
mode, is :mod:`~weathergen.engine.rendering.composite`'s. The sums' layout, :class:`Grids` (where
each grid level's planes sit), the levels a splat's stamps need (:func:`grids_for`) and the
scene depth on each (:func:`scene_depths`), is written here too.

These steps touch every pixel of every frame, for every channel, so on the CPU their cost is
the memory traffic: autograd's generic backward of the same expressions would allocate and fill
several full-size tensors more (zero gradients of slices), and the CPU backward of
``F.interpolate`` is several times slower than its forward. Each function here computes its
gradient in one allocation.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from .coarse import CoarseDepths, across_edges, drop_moments, footprint_depths
from .stamps import COARSE_MAX_LEVEL, StampSet

__all__ = ["Grids", "LayerPlanes", "Sums", "grids_for", "planes", "scene_depths", "upsample",
           "upsample_adjoint"]


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


def _phase_weights(factor: int, dtype, device) -> torch.Tensor:
    """The adjoint of linear upsampling by ``factor`` along one axis, per output phase r
    (source offset ``d_r = (2 r + 1 − f) / (2 f)``): row 0 sums a block, row 1 holds ``d_r`` of
    the phases that lean on the previous sample, row 2 those that lean on the next. Shape: (3, f).
    """
    half = factor // 2
    d = (2 * torch.arange(factor, dtype=torch.float64) + 1 - factor) / (2 * factor)
    w = torch.zeros(3, factor, dtype=torch.float64)
    w[0] = 1
    w[1, :half] = d[:half]
    w[2, half:] = d[half:]
    return w.to(dtype=dtype, device=device)


def _fold(s: torch.Tensor, a: torch.Tensor, b: torch.Tensor, dim: int) -> torch.Tensor:
    """Gather the three per-block sums of :func:`_phase_weights` onto the samples: output phases
    before a sample's centre blend it with the previous sample (weights ``1 + d``, ``−d``), those
    after it with the next one (``1 − d``, ``d``); the edges are replicated."""
    out = s + a - b
    n = out.shape[dim]
    head, tail = out.narrow(dim, 0, n - 1), out.narrow(dim, 1, n - 1)
    head -= a.narrow(dim, 1, n - 1)                  # −d of the next block's early phases
    tail += b.narrow(dim, 0, n - 1)                  # +d of the previous block's late phases
    out.narrow(dim, 0, 1).sub_(a.narrow(dim, 0, 1))  # the replicated sample before the first
    out.narrow(dim, n - 1, 1).add_(b.narrow(dim, n - 1, 1))
    return out


def upsample_adjoint(grad: torch.Tensor, factor: int,
                     coarse: Optional[Sequence[int]] = None) -> torch.Tensor:
    """The adjoint of :func:`upsample`. Shape: (C, 1, H, W) -> (C, 1, h, w), ``coarse`` = (h, w)
    (default: H / f, W / f), H <= f h and W <= f w (the rows and columns beyond a cropped
    gradient are zero).

    One axis at a time, an axis that needs no padding first: its pass reads the full-size
    gradient as it lies (one matrix product of the phase weights), and the other axis, then
    padded if cropped, works on an f times smaller tensor (no full-size copy).
    """
    height, width = grad.shape[-2:]
    h, w = (-(-height // factor), -(-width // factor)) if coarse is None else coarse
    w3 = _phase_weights(factor, grad.dtype, grad.device)

    def rows(g):        # (C, 1, f h, X) -> (C, 1, h, X)
        if g.shape[-2] < factor * h:
            g = F.pad(g, (0, 0, 0, factor * h - g.shape[-2]))
        return _fold(*(w3 @ g.unflatten(-2, (h, factor))).unbind(-2), dim=-2)

    def cols(g):        # (C, 1, X, f w) -> (C, 1, X, w)
        if g.shape[-1] < factor * w:
            g = F.pad(g, (0, factor * w - g.shape[-1]))
        return _fold(*(g.unflatten(-1, (w, factor)) @ w3.T).unbind(-1), dim=-1)

    if width == factor * w or height != factor * h:
        return rows(cols(grad))
    return cols(rows(grad))


class _Upsample(torch.autograd.Function):
    """Bilinear upsampling by an integer factor (``F.interpolate``, pixel centres aligned as in
    ``(x + 0.5) / f − 0.5``, edges replicated), cropped to ``size``; the backward pass applies
    the separable adjoint (the CPU backward of ``F.interpolate`` is several times slower than its
    forward)."""

    @staticmethod
    def forward(ctx, grid, factor, size):
        ctx.factor, ctx.full = factor, (grid.shape[-2] * factor, grid.shape[-1] * factor)
        ctx.size = size
        if tuple(size) == ctx.full:
            return F.interpolate(grid, scale_factor=factor, mode="bilinear", align_corners=False)
        try:    # the cropped result directly (ATen's kernel takes the size and the scale apart)
            return torch._C._nn.upsample_bilinear2d(grid, list(size), False, float(factor),
                                                    float(factor))
        except (AttributeError, TypeError, RuntimeError):
            out = F.interpolate(grid, scale_factor=factor, mode="bilinear", align_corners=False)
            return out[..., :size[0], :size[1]].contiguous()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):
        coarse = (ctx.full[0] // ctx.factor, ctx.full[1] // ctx.factor)
        return upsample_adjoint(grad.contiguous(), ctx.factor, coarse), None, None


def upsample(grid: torch.Tensor, factor: int, size: Sequence[int]) -> torch.Tensor:
    """Bilinear upsampling by an integer factor, cropped to ``size`` (at most ``f h, f w``).
    Shape: (C, 1, h, w) -> (C, 1, size[0], size[1])."""
    return _Upsample.apply(grid, factor, tuple(size))


class _Crop(torch.autograd.Function):
    """Every level's planes without margins (views of the sums); the backward pass writes the
    gradients into one tensor of the sums' shape, zeroing only the margins (autograd's slices
    would allocate and zero-fill one full-size tensor per slice). Shape: values (4, N) -> one
    (4, V, h, w) per level."""

    @staticmethod
    def forward(ctx, values, grids):
        ctx.grids, ctx.shape = grids, values.shape
        return tuple(grids.planes(values, index) for index in range(len(grids.levels)))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        grids = ctx.grids
        out = grads[0].new_empty(ctx.shape)
        for index, grad in enumerate(grads):
            _, offset, h, w, m = grids.levels[index]
            count = grids.count(index)
            size = count * (h + 1) * (w + 2 * m)
            full = out[:, offset:offset + size].view(out.shape[0], count, h + 1, w + 2 * m)
            full[..., h, :].zero_()
            full[..., :h, :m].zero_()
            full[..., :h, m + w:].zero_()
            if grad is None:
                full[..., :h, m:m + w].zero_()
            else:
                full[..., :h, m:m + w].copy_(grad)
        return out, None


def planes(sums: Sums) -> torch.Tensor:
    """The sums of every view on the image grid: each coarse grid cropped and upsampled to the
    image grid (across depth edges where the splat drew it against the footprints' nearest and
    farthest depths: :func:`~weathergen.engine.rendering.coarse.across_edges`), added coarsest first, then
    the image grid's own sums. A level that holds nothing of a view adds exact zeros to it, so a
    view's sums do not depend on which levels the other views of the call need. The moment
    sums of depth-aware coarse grids are used up here. Shape: -> (1 + C, V, 1, H, W) (a view of
    the sums where no coarse grid is drawn)."""
    grids, info = sums.grids, sums.coarse
    views = grids.views
    total = None
    for index, ((level, _, h, w, _), grid) in enumerate(
            zip(grids.levels, _Crop.apply(sums.values, grids))):
        if info is not None:
            moments = grid[info.moments:info.moments + 2]
            grid = drop_moments(grid, info)
        channels = grid.shape[0]
        if level:   # one plane per image: the kernel treats every plane alike, whatever V
            near = grid[:, :views]
            up = upsample(near.reshape(channels * views, 1, h, w), 2 ** level,
                          (grids.height, grids.width)).view(channels, views, grids.height,
                                                            grids.width)
            if info is not None:
                up = across_edges(up, near, grid[:, views:],
                                  (moments[0, :views], moments[1, :views], moments[0, views:],
                                   moments[1, views:]), info, index, level)
            grid = up
        total = grid if total is None else total + grid
    return total.view(total.shape[0], views, 1, grids.height, grids.width)


class LayerPlanes:
    """Every layer's sums on the image grid, frame by frame (layer ``k``'s values laid out as
    ``grids[k]`` says, views ``t B + b``), and their gradients.

    :meth:`read` brings a layer's coarse grids to the image grid (bilinear upsampling, coarsest
    first, then the image grid's own sums, as :func:`planes` adds them: a pixel covered by one
    layer sees that layer's sums of its record rendered alone).
    The gradient (:meth:`gradients`, then per frame and layer :meth:`buffer`, filled by the
    caller, and :meth:`finish`) is allocated uninitialised: the image grid's A and C planes are
    written whole through :meth:`buffer`, and only their margins, the depth plane and the
    (small) coarse grids are zero-filled; a layer drawn on coarse grids alone gets a
    full-size buffer whose adjoint upsampling :meth:`finish` adds to its grids."""

    def __init__(self, grids: Sequence[Grids], bsz: int):
        self.grids, self.bsz = list(grids), bsz

    def select(self, order: Sequence[int]) -> "LayerPlanes":
        return LayerPlanes([self.grids[k] for k in order], self.bsz)

    def _frame(self, t: int) -> slice:
        return slice(t * self.bsz, (t + 1) * self.bsz)

    def read(self, values: Sequence[torch.Tensor], t: int, k: int,
             channels: Optional[int] = None) -> torch.Tensor:
        """The first ``channels`` planes (default: all). Shape: -> (C, B, H, W) (a view of the
        sums where the layer has no coarse grid)."""
        grids, at = self.grids[k], self._frame(t)
        total = None
        for index, (level, _, h, w, _) in enumerate(grids.levels):
            grid = grids.planes(values[k], index)[:channels, at]           # (C, B, h, w)
            if level:
                up = upsample(grid.reshape(-1, 1, h, w), 2 ** level, (grids.height, grids.width))
                grid = up.view(grid.shape[0], grid.shape[1], grids.height, grids.width)
            total = grid if total is None else total + grid
        return total

    def gradients(self, values: Sequence[torch.Tensor]) -> list:
        out = []
        for grids, v in zip(self.grids, values):
            g = torch.empty_like(v)
            for level, offset, h, w, m in grids.levels:
                size = grids.views * (h + 1) * (w + 2 * m)
                if level:
                    g[:, offset:offset + size].zero_()
                    continue
                full = g[:, offset:offset + size].view(g.shape[0], grids.views, h + 1, w + 2 * m)
                full[..., h, :].zero_()
                full[..., :h, :m].zero_()
                full[..., :h, m + w:].zero_()
                full[4:, :, :h, m:m + w].zero_()
            out.append(g)
        return out

    def buffer(self, g_values: Sequence[torch.Tensor], t: int, k: int) -> torch.Tensor:
        """Where the gradient of frame ``t``'s A and C planes of layer ``k`` goes, (4, B, H, W):
        the image grid's planes, or a new tensor for a layer without one."""
        grids = self.grids[k]
        level = grids.levels[-1][0]
        if level == 0:
            return grids.planes(g_values[k], len(grids.levels) - 1)[:4, self._frame(t)]
        g = g_values[k]
        return g.new_empty((4, self.bsz, grids.height, grids.width))

    def finish(self, g_values: Sequence[torch.Tensor], buffer: torch.Tensor, t: int,
               k: int) -> None:
        """Add the adjoint upsampling of ``buffer`` (filled) to layer ``k``'s coarse grids."""
        grids, at = self.grids[k], self._frame(t)
        coarse = [(i, level, h, w) for i, (level, _, h, w, _) in enumerate(grids.levels) if level]
        if not coarse:
            return
        flat = buffer.reshape(-1, 1, grids.height, grids.width)
        for index, level, h, w in coarse:
            back = upsample_adjoint(flat, 2 ** level, (h, w))
            grids.planes(g_values[k], index)[:4, at].add_(back.view(4, self.bsz, h, w))
