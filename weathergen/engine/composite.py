"""Stage 4 of the render core: per-pixel sums -> weather frames and opacities.

The splat's :class:`~weathergen.engine.splat.Sums` hold, per view, ``A = Σ θ B V`` and
``C_c = Σ γ_c θ B V`` on the image grid and on the coarse grids of large billboards.
:func:`planes` brings the coarse grids to the image grid (bilinear upsampling, coarsest first)
and :func:`composite` blends: additive ``I + C`` or order-independent alpha ``I (1 − A) + C``
(Meshkin), each view with its record's mode, clamped to [0, 1]; the opacity is ``clamp(A, 0, 1)``.
:func:`composite_in_order` draws records whose blur samples are blended one after another (the
research code's order, ``RenderSettings.blur_blend = "sequential"``): a splat per sample place,
blended step by step.

Both steps touch every pixel of every frame, for every channel, so on the CPU their cost is the
memory traffic: autograd's generic backward of the same expressions would allocate and fill
several full-size tensors more (zero gradients of slices, the stack that undoes an ``unbind``,
masks of each ``clamp``). Each function here computes its gradient in one allocation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from .coarse import across_edges, drop_moments
from .splat import Sums, splat
from .stamps import StampSet
from .tracks import Instances, Tracks, blur_samples


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


@dataclass
class RenderOutput:
    """Shape: image1, image2 (B, 3, H, W) in [0, 1]; opacity1, opacity2 (B, 1, H, W) in [0, 1];
    reached (B,) bool: which pairs' frames any blur sample of their record was splatted into (a
    pair that none reached has frames that do not depend on its particles)."""

    image1: torch.Tensor
    image2: torch.Tensor
    opacity1: torch.Tensor
    opacity2: torch.Tensor
    reached: Optional[torch.Tensor] = None


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
    farthest depths: :func:`~weathergen.engine.coarse.across_edges`), added coarsest first, then
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


class _Blend(torch.autograd.Function):
    """T frames of a batch of B blended with their sums: ``I (1 − A) + C`` (alpha) or ``I + C``
    (additive), clamped to [0, 1], and the opacity ``clamp(A, 0, 1)``.

    Shape: sums (4, T, B, 1, H, W) (A, C_r, C_g, C_b per frame), alpha_mode (B,) bool, images T
    tensors (B, 3, H, W) -> T images (B, 3, H, W), then T opacities (B, 1, H, W).
    Gradients flow to the sums and the images; a clamped value passes none (as ``clamp``).
    """

    @staticmethod
    def forward(ctx, sums, alpha_mode, *images):
        mode = alpha_mode.view(-1, 1, 1, 1)
        all_alpha, no_alpha = bool(alpha_mode.all()), not bool(alpha_mode.any())
        grad = any(ctx.needs_input_grad[:1] + ctx.needs_input_grad[2:])
        outs, opacities, masks = [], [], []
        for t, image in enumerate(images):
            alpha = sums[0, t]                                           # (B, 1, H, W)
            colour = sums[1:, t, :, 0].transpose(0, 1)                   # (B, 3, H, W)
            if all_alpha:
                pre = torch.addcmul(colour, image, 1 - alpha)
            elif no_alpha:
                pre = image + colour
            else:   # (the same operations as above: a pair's bits do not depend on the batch)
                pre = torch.where(mode, torch.addcmul(colour, image, 1 - alpha), image + colour)
            if grad:    # where clamp passes the gradient: the value lies in [0, 1]
                out, opacity = pre.clamp(0, 1), alpha.clamp(0, 1)
                masks += [out == pre, opacity == alpha]
            else:
                out, opacity = pre.clamp_(0, 1), alpha.clamp(0, 1)
            outs.append(out)
            opacities.append(opacity)
        if grad:
            ctx.save_for_backward(sums, alpha_mode, *images, *masks)
        ctx.frames = len(images)
        return (*outs, *opacities)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        frames = ctx.frames
        sums, alpha_mode, *rest = ctx.saved_tensors
        images, masks = rest[:frames], rest[frames:]
        g_outs, g_ops = grads[:frames], grads[frames:]
        mode = alpha_mode.view(-1, 1, 1, 1).to(sums.dtype)
        g_sums = sums.new_empty(sums.shape) if ctx.needs_input_grad[0] else None
        g_images = []
        for t, (image, g_out, g_op) in enumerate(zip(images, g_outs, g_ops)):
            mask_out, mask_op = masks[2 * t], masks[2 * t + 1]
            if g_sums is not None:      # dL/dC: the output gradient where it passes the clamp
                g = g_sums[1:, t, :, 0].transpose(0, 1)                      # (B, 3, H, W)
                if g_out is None:
                    g.zero_()
                else:
                    torch.mul(g_out, mask_out, out=g)
            else:
                g = torch.zeros_like(image) if g_out is None else g_out * mask_out
            g_images.append(g * (1 - sums[0, t] * mode) if ctx.needs_input_grad[2 + t] else None)
            if g_sums is None:
                continue
            g_alpha = g_sums[0, t]                                           # (B, 1, H, W)
            if bool(alpha_mode.any()):     # dL/dA = −Σ_c g_c I_c (alpha blending) + opacity's
                torch.mul(g[:, :1], image[:, :1], out=g_alpha)
                for c in (1, 2):
                    g_alpha.addcmul_(g[:, c:c + 1], image[:, c:c + 1])
                g_alpha.mul_(-mode)
            else:
                g_alpha.zero_()
            if g_op is not None:
                g_alpha.addcmul_(g_op, mask_op.to(g_op.dtype))
        return (g_sums, None, *g_images)


def blend(sums: torch.Tensor, image1: torch.Tensor, image2: torch.Tensor,
          alpha_mode: torch.Tensor):
    """Both frames of a batch of pairs (see :class:`_Blend`; sums (4, 2, B, 1, H, W)).
    Returns (image1, image2, opacity1, opacity2)."""
    return _Blend.apply(sums, alpha_mode, image1, image2)


def composite(sums: Sums, images: Sequence[torch.Tensor], alpha_mode: torch.Tensor) -> tuple:
    """The weather frames: view ``t B + b`` of the sums is frame ``t`` of image batch ``b``.

    Shape: images T tensors (B, 3, H, W) (V = T B views), alpha_mode (B,) bool -> (T images
    (B, 3, H, W), T opacities (B, 1, H, W)).
    """
    frames = len(images)
    bsz, _, height, width = images[0].shape
    grid = planes(sums).view(4, frames, bsz, 1, height, width)
    out = _Blend.apply(grid, alpha_mode, *images)
    return list(out[:frames]), list(out[frames:])


# -- blur samples blended one after another (the research code's order) ----------------------

def sample_places(inst: Instances, ordered_views: torch.Tensor) -> torch.Tensor:
    """Each blur sample's place ``k`` along its streak (0 for the streak's start, as
    :func:`~weathergen.engine.tracks.blur_samples` lays them out: a track's samples consecutive,
    no two consecutive tracks of the same entry and view) where its view is in
    ``ordered_views``, 0 elsewhere. Shape: I instances, ordered_views (V,) bool -> (I,) int64."""
    n = inst.count
    index = torch.arange(n, device=inst.entry.device)
    starts = torch.ones(n, dtype=torch.bool, device=index.device)
    starts[1:] = (inst.entry[1:] != inst.entry[:-1]) | (inst.view[1:] != inst.view[:-1])
    first = torch.cummax(torch.where(starts, index, 0), 0).values if n else index
    return torch.where(ordered_views.index_select(0, inst.view), index - first, 0)


def composite_in_order(tracks: Tracks, stamps: StampSet, depth: torch.Tensor,
                       images: Sequence[torch.Tensor], alpha_mode: torch.Tensor,
                       ordered: torch.Tensor, *, chunk_elements: Optional[int] = None,
                       detach_occlusion: bool = False) -> tuple:
    """The weather frames with the blur samples of the ``ordered`` pairs blended one after
    another, as the research code draws them: sample ``k`` of every streak of the pair (``k``
    from the streak's start; each streak its record's K samples, none added on long streaks)
    splatted alone and blended over the frame that samples ``0 .. k − 1`` left,
    ``I_k = clamp(I_{k−1} (1 − A_k) + C_k, 0, 1)`` (alpha; ``I_{k−1} + C_k`` additive), with
    the opacity ``1 − Π_k (1 − clamp(A_k, 0, 1))``. The other pairs' samples are all in step 0,
    the later steps leave their frames as they are: the same bytes as :func:`composite`.

    One splat draws every step, step ``k``'s samples into views ``k V + v`` (depth repeated), so
    memory grows with the number of steps; gradients flow as through :func:`composite` (each
    step's blend is :class:`_Blend`).
    Shape: tracks of V = T B views, depth (V, 1, H, W), images T tensors (B, 3, H, W),
    alpha_mode and ordered (B,) bool -> (T images (B, 3, H, W), T opacities (B, 1, H, W),
    reached (V,) bool).
    """
    frames = len(images)
    bsz, _, height, width = images[0].shape
    views = frames * bsz
    ordered_views = ordered.to(tracks.entry.device).repeat(frames)
    # the research code's K samples per streak: no samples added on long streaks
    gap = stamps.gap.clone()
    gap[tracks.entry[ordered_views.index_select(0, tracks.view)]] = float("inf")
    inst = blur_samples(tracks, images[0].dtype, gap)
    place = sample_places(inst, ordered_views)
    steps = int(place.max()) + 1 if inst.count else 1
    inst = dataclasses.replace(inst, view=place * views + inst.view)
    sums = splat(inst, stamps, depth.repeat(steps, 1, 1, 1), chunk_elements=chunk_elements,
                 detach_occlusion=detach_occlusion)
    grid = planes(sums).view(4, steps, frames, bsz, 1, height, width)
    outs, opacities = list(images), None
    for step in grid.unbind(1):
        blended = _Blend.apply(step, alpha_mode, *outs)
        outs, alphas = list(blended[:frames]), blended[frames:]
        opacities = list(alphas) if opacities is None else \
            [torch.addcmul(o, a, 1 - o) for o, a in zip(opacities, alphas)]
    return outs, opacities, sums.reached.view(steps, views).any(0)
