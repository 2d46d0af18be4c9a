"""Stage 4 of the render core: the blend modes, weather sums -> frames and opacities.

Every way weather is blended into frames lives here, each with its hand-written backward pass;
the sums arrive on the image grid from :mod:`~weathergen.engine.rendering.planes`.

One record per pair (:func:`composite`, :class:`_Blend`): each view's planes blend additive
``I + C`` or with order-independent alpha ``I (1 − A) + C`` (Meshkin), each view with its record's
mode, clamped to [0, 1]; the opacity is ``clamp(A, 0, 1)``. :func:`composite_in_order` draws
records whose blur samples are blended one after another (the research code's order,
``RenderSettings.blur_blend = "sequential"``): a splat per sample place, blended step by step.

Combined weather (:func:`blend_layers`; the layers drawn by
:mod:`~weathergen.engine.rendering.combined`): at every pixel the alpha layers are ordered by their mean
depth ``Z / A``, far to near, and blended one over the other (``I (1 − A) + C``), then the
additive layers' light is added (``+ C``), clamped to [0, 1] once at the end; the opacity is
``1 − Π (1 − clamp(A_l, 0, 1))``. Within a layer the particles keep the order-independent sums
of a single preset. Two layers, one additive and one alpha-blended (snow, rain or sparks with
fog), and two additive layers have closed forms with a few full-frame passes
(:class:`_AdditiveOverAlpha`, :class:`_AdditivePair`, through :class:`_TwoLayers`); other
combinations go through a sorting network (:class:`_LayeredBlend`, in which a dimmed additive
layer sorts as the nearest). Where every layer blends additively the order changes nothing: no
layer is dimmed and none carries a depth sum (two layers), or all are sorted as alpha layers
of zero opacity. The order is a step function of the depths: gradients flow through every
layer's ``A`` and ``C``, not through which layer is in front.

Blending touches every pixel of every frame, for every channel, so on the CPU its cost is the
memory traffic: autograd's generic backward of the same expressions would allocate and fill
several full-size tensors more (the stack that undoes an ``unbind``, masks of each ``clamp``);
the backward passes here write their gradients into buffers allocated once.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from .planes import LayerPlanes, Sums, planes
from .splat import splat
from .stamps import StampSet
from .tracks import Instances, Tracks, blur_samples

__all__ = ["RenderOutput", "blend", "blend_layers", "composite", "composite_in_order",
           "fog", "fogged_opacity", "tinted"]


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


def fog(airlight: torch.Tensor, image: torch.Tensor, transmission: torch.Tensor) -> torch.Tensor:
    """The scene seen through the air (Koschmieder): ``J t + A (1 − t)``. Shape: broadcast."""
    return torch.lerp(airlight, image, transmission)


def fogged_opacity(opacity: torch.Tensor, transmission: torch.Tensor) -> torch.Tensor:
    """The weather's opacity with the air's in front of the scene: ``1 − t (1 − α)``."""
    return 1 - transmission * (1 - opacity)


def tinted(colour: torch.Tensor, passed: torch.Tensor, transmission: torch.Tensor,
           airlight: torch.Tensor) -> torch.Tensor:
    """Alpha-blended particles' colours through the air in front of them, ``γ t_p + A_p (1 − t_p)``
    (``passed``: ``t_p`` in the colours' dtype). Shape: (N, 3), (N,), (N,), (N, 3) -> (N, 3)."""
    light = ((1 - transmission)[:, None] * airlight).to(passed.dtype)
    return colour * passed[:, None] + light


# -- one record per pair ----------------------------------------------------------------------

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
            else:
                # (the same operations as above: a pair's bits do not depend on the batch)
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


# -- combined weather: layers in depth order --------------------------------------------------

def blend_layers(sums: Sequence[Sums], modes: Sequence[set], alpha_mode: torch.Tensor,
                 images: Sequence[torch.Tensor]) -> tuple:
    """The frames of combined weather: every layer's sums (views ``t B + b``: frame ``t`` of
    image batch ``b``; with the depth sum ``Z`` as a fifth plane, except an additive layer
    dimmed by alpha layers and two additive layers), each layer blended with its mode, per
    pixel in depth order (see the module doc). ``modes[k]``: the blend modes layer ``k`` has
    across the pairs. Two additive layers, or an additive and an alpha-blended one, take a
    closed form; any other combination the sorting network.

    Shape: alpha_mode (B, L) bool, images T tensors (B, 3, H, W) -> T images (B, 3, H, W), then
    T opacities (B, 1, H, W).
    """
    layout = LayerPlanes([s.grids for s in sums], images[0].shape[0])
    values = [s.values for s in sums]
    if list(modes) == [{"additive"}, {"additive"}]:      # their order changes nothing
        return _TwoLayers.apply(_AdditivePair, layout, *values, *images)
    if len(modes) == 2 and {"additive"} in modes and {"alpha"} in modes:
        order = (0, 1) if modes[0] == {"additive"} else (1, 0)      # the additive layer first
        return _TwoLayers.apply(_AdditiveOverAlpha, layout.select(order),
                                *(values[k] for k in order), *images)
    return _LayeredBlend.apply(alpha_mode, layout, len(values), *values, *images)


def _split(planes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A layer's planes (C, B, H, W) -> A (B, 1, H, W), C (B, 3, H, W) (views)."""
    return planes[0].unsqueeze(1), planes[1:4].transpose(0, 1)


def _clamp_passed(pre: torch.Tensor, grad: bool) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """``clamp(pre, 0, 1)`` and, with gradients, where the clamp passes them."""
    if not grad:
        return pre.clamp_(0, 1), None
    out = pre.clamp(0, 1)
    return out, out == pre


def _inside(clear: torch.Tensor) -> torch.Tensor:
    """Where ``clear = 1 − clamp(A, 0, 1)`` passes a gradient to A."""
    return (clear > 0) & (clear < 1)


class _TwoLayers(torch.autograd.Function):
    """Two layers composited per pixel in closed form (:class:`_AdditiveOverAlpha`,
    :class:`_AdditivePair`): the frames' loops and the gradient buffers here, the arithmetic of
    one frame in the form.

    Shape: form the closed form; layout a
    :class:`~weathergen.engine.rendering.planes.LayerPlanes` (the layers in the form's order);
    values the two layers' sums; images T tensors (B, 3, H, W) -> T images (B, 3, H, W), then T
    opacities (B, 1, H, W).
    """

    @staticmethod
    def forward(ctx, form, layout, values_0, values_1, *images):
        values = (values_0, values_1)
        grad = any(ctx.needs_input_grad)
        one = images[0].new_ones(())
        outs, opacities, saved = [], [], []
        for t, image in enumerate(images):
            # (the closed forms read no depth sum: A and C alone)
            out, opacity, kept = form.frame(layout.read(values, t, 0, 4),
                                            layout.read(values, t, 1, 4), image, one, grad)
            outs.append(out)
            opacities.append(opacity)
            if grad:
                saved.append(kept)
        ctx.form, ctx.saved, ctx.layout, ctx.shapes = form, saved, layout, values
        return (*outs, *opacities)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        layout, frames = ctx.layout, len(ctx.saved)
        g_values = layout.gradients(ctx.shapes)
        g_images = []
        for t, kept in enumerate(ctx.saved):
            buffers = [layout.buffer(g_values, t, k) for k in (0, 1)]
            g_images.append(ctx.form.frame_backward(kept, grads[t], grads[frames + t],
                                                    *(_split(b) for b in buffers),
                                                    ctx.needs_input_grad[4 + t]))
            for k, b in enumerate(buffers):
                layout.finish(g_values, b, t, k)
        return (None, None, *g_values, *g_images)


class _AdditiveOverAlpha:
    """Two layers, the first additive and the second alpha-blended in every pair (snow, rain or
    sparks with fog), composited in closed form (through :class:`_TwoLayers`). The additive
    layer's particles behind the alpha layer were dimmed before the splat
    (:mod:`~weathergen.engine.rendering.combined`), so its light goes on top: ``C_a + I k + C_s`` with
    ``k = 1 − A_a`` (the alpha layer's transmission); the opacity
    ``1 − (1 − clamp(A_s)) clamp(k)``. The additive layer's planes hold no depth sum.
    """

    @staticmethod
    def frame(planes_s, planes_a, image, one, grad: bool):
        alpha_s, colour_s = _split(planes_s)
        alpha_a, colour_a = _split(planes_a)
        keep = 1 - alpha_a
        pre = torch.addcmul(colour_a, image, keep).add_(colour_s)
        out, passed = _clamp_passed(pre, grad)
        clear_s, clear_a = 1 - alpha_s.clamp(0, 1), keep.clamp(0, 1)
        opacity = torch.addcmul(one, clear_s, clear_a, value=-1)
        return out, opacity, (keep, passed, image, clear_s, clear_a)

    @staticmethod
    def frame_backward(kept, g_out, g_op, grads_s, grads_a, need_image: bool):
        keep, passed, image, clear_s, clear_a = kept
        (g_alpha_s, g_colour_s), (g_alpha_a, g) = grads_s, grads_a
        if g_out is None:                       # dL/dC_a = dL/dC_s: what passes the clamp
            g.zero_()
        else:
            torch.mul(g_out, passed, out=g)
        g_colour_s.copy_(g)
        # dL/dA_a = −Σ_c g_c I_c
        torch.mul(g[:, :1], image[:, :1], out=g_alpha_a)
        for c in (1, 2):
            g_alpha_a.addcmul_(g[:, c:c + 1], image[:, c:c + 1])
        g_alpha_a.neg_()
        if g_op is None:
            g_alpha_s.zero_()
        else:       # d(1 − clear_s clear_a)/dA: the other layer's clear, inside the clamp
            torch.mul(g_op * clear_a, _inside(clear_s), out=g_alpha_s)
            g_alpha_a.addcmul_(g_op * clear_s, _inside(clear_a))
        return g * keep if need_image else None


class _AdditivePair:
    """Two additive layers (through :class:`_TwoLayers`): their order changes nothing
    (``I + C_1 + C_2``), so they carry no depth sum; ``I + (C_1 + C_2)`` whichever layer is
    listed first. The opacity ``1 − (1 − clamp(A_1)) (1 − clamp(A_2))``.
    """

    @staticmethod
    def frame(planes_1, planes_2, image, one, grad: bool):
        (alpha_1, colour_1), (alpha_2, colour_2) = _split(planes_1), _split(planes_2)
        out, passed = _clamp_passed((colour_1 + colour_2).add_(image), grad)
        clear_1, clear_2 = 1 - alpha_1.clamp(0, 1), 1 - alpha_2.clamp(0, 1)
        return out, torch.addcmul(one, clear_1, clear_2, value=-1), (passed, clear_1, clear_2)

    @staticmethod
    def frame_backward(kept, g_out, g_op, grads_1, grads_2, need_image: bool):
        passed, clear_1, clear_2 = kept
        (g_alpha_1, g_colour_1), (g_alpha_2, g_colour_2) = grads_1, grads_2
        if g_out is None:
            g_colour_1.zero_()
        else:
            torch.mul(g_out, passed, out=g_colour_1)
        g_colour_2.copy_(g_colour_1)
        if g_op is None:
            g_alpha_1.zero_()
            g_alpha_2.zero_()
        else:
            torch.mul(g_op * clear_2, _inside(clear_1), out=g_alpha_1)
            torch.mul(g_op * clear_1, _inside(clear_2), out=g_alpha_2)
        return g_colour_1.clone() if need_image else None


class _LayeredBlend(torch.autograd.Function):
    """T frames of a batch of B pairs with L layers each, composited per pixel far to near.

    The order is a sorting network of compare-and-swap steps on whole frames (``L (L − 1) / 2``
    of them: one for two layers), each a few elementwise selections whose masks the backward
    pass replays (a layer that covers a pixel not at all blends nothing there, wherever it
    sorts; with three layers or more it sorts as the nearest, mean depth 0, so that it never
    stands between two others unordered). An additive layer blends as one of zero opacity:
    ``I (1 − 0) + C``; a dimmed one (:mod:`~weathergen.engine.rendering.combined`) has no depth sum and
    sorts as the nearest (mean depth 0). Layer ``k`` is nearer than layer ``j`` where ``Z_k A_j < Z_j A_k`` (mean
    depths compared without a division).

    Shape: values as ``layout`` reads them (each layer's sums, or whole planes), each frame
    and layer's planes (5, B, H, W) (A, C_r, C_g, C_b, Z; 4 without Z); alpha_mode (B, L) bool; images T
    tensors (B, 3, H, W) -> T images (B, 3, H, W), then T opacities (B, 1, H, W). Gradients flow
    to the A and C planes and the images.
    """

    @staticmethod
    def forward(ctx, alpha_mode, layout, count, *tensors):
        values, images = tensors[:count], tensors[count:]
        nl = alpha_mode.shape[1]
        mode = alpha_mode.to(values[0].dtype)[:, :, None, None]             # (B, L, 1, 1)
        every = alpha_mode.all(0).tolist()      # layers alpha-blended in every pair: A as is
        grad = any(ctx.needs_input_grad)
        one, zero = values[0].new_ones(()), values[0].new_zeros(())
        outs, opacities, saved = [], [], []
        for t, image in enumerate(images):
            planes = [layout.read(values, t, k) for k in range(nl)]         # (5, B, H, W) each
            alpha = [p[0].unsqueeze(1) for p in planes]                     # (B, 1, H, W)
            # (a dimmed additive layer has no depth sum: it blends as the nearest)
            depth = [p[4].unsqueeze(1) if p.shape[0] > 4 else zero for p in planes]
            cover = [alpha[k] if every[k] else alpha[k] * mode[:, k, None] for k in range(nl)]
            paint = [p[1:4].transpose(0, 1) for p in planes]                # (B, 3, H, W)
            if nl > 2:      # a layer absent from a pixel sorts as the nearest (mean depth 0)
                alpha, depth = ([torch.where(a > 0, x, fill) for a, x in zip(alpha, xs)]
                                for xs, fill in ((alpha, one), (depth, zero)))
            swaps = []
            for top in range(nl - 1, 0, -1):     # bubble the nearest layer to the end
                for k in range(top):
                    swap = depth[k] * alpha[k + 1] < depth[k + 1] * alpha[k]   # k nearer
                    swaps.append((k, swap))
                    moved = (cover, paint) if top == 1 else (alpha, depth, cover, paint)
                    for x in moved:
                        x[k], x[k + 1] = (torch.where(swap, x[k + 1], x[k]),
                                          torch.where(swap, x[k], x[k + 1]))
            under, keep = [image], [1 - c for c in cover]
            for k in range(nl):
                under.append(torch.addcmul(paint[k], under[-1], keep[k]))
            pre = under.pop()
            out = pre.clamp(0, 1) if grad or not nl else pre.clamp_(0, 1)
            clear = [1 - p[0].unsqueeze(1).clamp(0, 1) for p in planes]
            total = clear[0]
            for c in clear[1:]:
                total = total * c
            outs.append(out)
            opacities.append((1 - total).clamp_(0, 1))
            if grad:
                saved.append((swaps, keep, under, out == pre, clear))
        ctx.saved, ctx.layout = saved, layout
        ctx.values, ctx.mode = values, mode
        return (*outs, *opacities)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        frames = len(ctx.saved)
        layout = ctx.layout
        g_values = layout.gradients(ctx.values)
        g_images = []
        for t, (swaps, keep, under, passed, clear) in enumerate(ctx.saved):
            g_out, g_op = grads[t], grads[frames + t]
            nl = len(keep)
            g = (torch.zeros_like(under[0]) if g_out is None else g_out * passed)
            g_cover, g_paint = [None] * nl, [None] * nl
            for k in range(nl - 1, -1, -1):
                g_paint[k] = g
                g_cover[k] = (g * under[k]).sum(1, keepdim=True)      # negated below
                g = g * keep[k]
            g_images.append(g)
            for k, swap in reversed(swaps):
                for x in (g_cover, g_paint):
                    x[k], x[k + 1] = (torch.where(swap, x[k + 1], x[k]),
                                      torch.where(swap, x[k], x[k + 1]))
            for k in range(nl):
                g_alpha = g_cover[k] * -ctx.mode[:, k, None]
                if g_op is not None:      # d(1 − Π clear)/dA_k = Π_{j≠k} clear_j where 0 < A_k < 1
                    others = None
                    for j in range(nl):
                        if j != k:
                            others = clear[j] if others is None else others * clear[j]
                    inside = _inside(clear[k])
                    g_alpha = g_alpha + g_op * others * inside
                buffer = layout.buffer(g_values, t, k)
                g_a, g_c = _split(buffer)
                g_a.copy_(g_alpha)
                g_c.copy_(g_paint[k])
                layout.finish(g_values, buffer, t, k)
        return (None, None, None, *g_values, *g_images)


# -- blur samples blended one after another (the research code's order) ----------------------

def sample_places(inst: Instances, ordered_views: torch.Tensor) -> torch.Tensor:
    """Each blur sample's place ``k`` along its streak (0 for the streak's start, as
    :func:`~weathergen.engine.rendering.tracks.blur_samples` lays them out: a track's samples consecutive,
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
