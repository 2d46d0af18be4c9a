"""Combined weather in one pass: every layer of a :class:`~weathergen.engine.LayeredParticles`
drawn by the one render core, then composited per pixel in depth order.

The layers of a pair are laid out as more records of the same call: layer ``l`` of pair ``b``
is pseudo-pair ``q = b L + l`` whose two views carry pair ``b``'s cameras and scene depth. So
the tracks, stamps and splat stages run once over the particles of every layer (each layer's
stamps from its own template library, each layer's looks and settings its own), and the splat
leaves one set of planes per layer and view. Each blur sample carries its camera depth ``z`` as
a fourth colour channel, so the planes hold a fifth sum ``Z = Σ θ B V z`` beside
``A = Σ θ B V`` and ``C = Σ γ θ B V``.

Composite (:func:`composite_layers`): at every pixel the layers are ordered by their
opacity-weighted mean depth ``Z / A``, far to near, and blended one over the other, each with its
own blend mode (additive ``I + C``, alpha ``I (1 − A) + C``), clamped to [0, 1] once at the end;
the opacity is ``1 − Π (1 − clamp(A_l, 0, 1))``. Within a layer the particles keep the
order-independent sums of a single preset.

The approximation and its limits: a layer is ordered as one surface per pixel, at its mean
depth there. Where the particles of two layers covering a pixel lie on the same side of each
other (a near snow flake over far fog, or a near fog billboard over far snow) the order is
exact; where they interleave in depth (fog in front of and behind the same flake) the pixel
sees one layer wholly in front of the other, by their mean depths. The order is a step function
of the depths, so gradients flow through every layer's ``A`` and ``C`` (to colours, offsets and
transparencies, as in a single render), not through which layer is in front. A pair rendered
with one layer gives the bytes of its record rendered alone.
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence, Union

import torch

from ..errors import ConfigError
from .composite import RenderOutput, upsample, upsample_adjoint
from .layers import LayeredParticles
from .particles import Particles
from .splat import chunk_elements_for, splat
from .stamps import COARSE_SIDE, StampSet, build
from .templates import TemplateLibrary, load_templates
from .tracks import (Looks, ParticleTable, RecordRows, Tracks, Views, blur_samples, empty_looks,
                     fixed_looks, pair_tracks)

__all__ = ["as_layers", "build_layer_stamps", "composite_layers", "render_layers"]


def as_layers(particles: Union[Particles, LayeredParticles, Sequence]) -> list[LayeredParticles]:
    """One :class:`LayeredParticles` per pair (a plain record is one layer); ConfigError unless
    every pair has the same number of layers."""
    items = [particles] if isinstance(particles, (Particles, LayeredParticles)) else list(particles)
    out = [p if isinstance(p, LayeredParticles) else LayeredParticles((p,), ("",)) for p in items]
    counts = sorted({len(p.layers) for p in out})
    if len(counts) > 1:
        raise ConfigError(f"the pairs of one render call must have the same number of weather "
                          f"layers; got {', '.join(map(str, counts))}")
    return out


def _libraries(records: Sequence[Particles]) -> dict[str, TemplateLibrary]:
    """Each template library the records name, checked against the records sampled with it."""
    libs: dict[str, TemplateLibrary] = {}
    for r in records:
        name = r.settings.templates
        if name not in libs:
            libs[name] = load_templates(name)
        lib = libs[name]
        if r.settings.templates_digest and lib.digest != r.settings.templates_digest:
            raise ConfigError(f"particles were sampled with templates '{name}' (digest "
                              f"{r.settings.templates_digest}) but are rendered with "
                              f"'{lib.name}' (digest {lib.digest})")
    return libs


def _parts(records: Sequence[Particles], views: Views, libs: dict, *, beta: float, dtype,
           paper: bool) -> list[tuple[Looks, Tracks, TemplateLibrary]]:
    """Looks and tracks of the records of one model (``paper``: the paper's, else fields), one
    part per template library, in the order the libraries are first named; record ``q`` is
    pseudo-pair ``q``."""
    out = []
    for name, lib in libs.items():
        chosen = [q for q, r in enumerate(records) if r.settings.templates == name and r.count
                  and (r.optics is None) == paper]
        if chosen:
            looks, tracks = pair_tracks([records[q] for q in chosen], views, lib.resolution,
                                        beta=beta, dtype=dtype, pairs=chosen)
            out.append((looks, tracks, lib))
    return out


def _flat(layered: Sequence[LayeredParticles]) -> list[Particles]:
    return [r for p in layered for r in p.layers]


def build_layer_stamps(particles: Union[LayeredParticles, Sequence[LayeredParticles]], *,
                       dtype: torch.dtype = torch.float32, device=None,
                       coarse_side: Optional[int] = COARSE_SIDE) -> StampSet:
    """The stamps of the layers' particles of the paper's model, in the order
    :func:`render_layers` draws them (reusable across attack steps, as
    :func:`~weathergen.engine.build_stamps` for a single record)."""
    layered = as_layers(particles)
    records = _flat(layered)
    device = torch.device(device) if device is not None else records[0].device
    libs = _libraries(records)
    with torch.no_grad():
        parts = []
        for name, lib in libs.items():
            chosen = [r.to(device) for r in records if r.settings.templates == name and r.count
                      and r.optics is None]
            if chosen:
                looks = fixed_looks(ParticleTable.of(chosen, device),
                                    RecordRows.of(chosen, device), lib.resolution)
                parts.append(build(looks, lib, dtype=dtype, coarse_side=coarse_side))
        if not parts:
            return build(empty_looks(device), next(iter(libs.values())), dtype=dtype)
        return StampSet.cat(parts)


def render_layers(image1: torch.Tensor, image2: torch.Tensor, depth1: torch.Tensor,
                  depth2: torch.Tensor, intrinsics: torch.Tensor, cam1_from_ref: torch.Tensor,
                  cam2_from_ref: torch.Tensor, particles: Sequence[LayeredParticles], *,
                  beta: float, stamps: Optional[StampSet] = None,
                  chunk_elements: Optional[int] = None, coarse_side: Optional[int] = COARSE_SIDE,
                  detach_occlusion: bool = False) -> RenderOutput:
    """Render the layers of each pair of a batch in one pass (see the module doc).

    Shape: as :func:`~weathergen.engine.render` (images (B, 3, H, W), ...); ``particles`` one
    :class:`LayeredParticles` per pair, each with the same number L of layers. ``stamps``: from
    :func:`build_layer_stamps` of the same layers.
    """
    layered = as_layers(particles)
    bsz, _, height, width = image1.shape
    nl = len(layered[0].layers)
    dtype, device = image1.dtype, image1.device
    records = _flat(layered)                               # record q = b L + l
    libs = _libraries(records)
    for r in records:
        if r.settings.blend not in ("additive", "alpha"):
            raise ConfigError(f"unknown blend mode {r.settings.blend!r}")
    rep = lambda t: t.to(device).repeat_interleave(nl, 0)  # noqa: E731  (pair b -> its L layers)
    views = Views.of(torch.cat((rep(intrinsics), rep(intrinsics))),
                     torch.cat((rep(cam1_from_ref), rep(cam2_from_ref))),
                     torch.cat((rep(depth1), rep(depth2))), device=device)
    paper = _parts(records, views, libs, beta=float(beta), dtype=dtype, paper=True)
    field = _parts(records, views, libs, beta=float(beta), dtype=dtype, paper=False)
    if chunk_elements is None:
        chunk_elements = chunk_elements_for(device)
    if stamps is None:
        stamp_parts = [build(looks, lib, dtype=dtype, coarse_side=coarse_side,
                             chunk_elements=chunk_elements) for looks, _, lib in paper]
    else:
        count = sum(looks.count for looks, _, _ in paper)
        if stamps.count != count:
            raise ConfigError(f"stamps hold {stamps.count} entries but the layers hold {count} "
                              f"particles of the paper's model (build them from these layers)")
        stamp_parts = [stamps.to(dtype, device)]
    stamp_parts += [build(looks, lib, dtype=dtype, coarse_side=coarse_side,
                          chunk_elements=chunk_elements) for looks, _, lib in field]
    parts = paper + field
    if parts:
        offsets = [0]
        for looks, _, _ in parts[:-1]:
            offsets.append(offsets[-1] + looks.count)
        tracks = Tracks.cat([t for _, t, _ in parts], offsets)
        stamp_set = StampSet.cat(stamp_parts)
    else:
        tracks = pair_tracks([], views, 1, beta=float(beta), dtype=dtype)[1]
        stamp_set = build(empty_looks(device), next(iter(libs.values())), dtype=dtype)
    inst = blur_samples(tracks, dtype)
    inst = dataclasses.replace(inst, color=torch.cat((inst.color, inst.z.detach()[:, None]), 1))
    sums = splat(inst, stamp_set, views.depth, chunk_elements=chunk_elements,
                 detach_occlusion=detach_occlusion, image_grid=True)   # (read by _SumsLayout)
    alpha_mode = torch.tensor([[r.settings.blend == "alpha" for r in p.layers] for p in layered],
                              device=device)
    layout = _SumsLayout(sums.grids, _coarse_use(stamp_set, inst, bsz, nl), bsz, nl)
    out1, out2, opacity1, opacity2 = _LayeredBlend.apply(sums.values, alpha_mode, layout,
                                                         image1, image2)
    return RenderOutput(image1=out1, image2=out2, opacity1=opacity1, opacity2=opacity2,
                        reached=sums.reached.view(2, bsz, nl).any(2).any(0))


def _coarse_use(stamps: StampSet, inst, bsz: int, nl: int) -> set:
    """``(level, t, k)`` for every grid level (the image grid's 0 included) that frame ``t`` of
    layer ``k`` draws on (in some pair of the batch); empty where no stamp is coarse (every
    layer reads the image grid alone). One host synchronisation."""
    if not stamps.count or not inst.count or int(stamps.coarse.max()) == 0:
        return set()
    with torch.no_grad():
        level = stamps.coarse.index_select(0, inst.entry)
        t, k = torch.div(inst.view, bsz * nl, rounding_mode="floor"), inst.view % nl
        key = torch.unique((level * 2 + t) * nl + k).tolist()
    return {(q // (2 * nl), q // nl % 2, q % nl) for q in key}


class _SumsLayout:
    """Where the planes of frame ``t``, layer ``k`` of every pair lie in the splat's flat sums
    (views ``t B L + b L + k``), and how a coarse grid reaches the image grid (bilinear
    upsampling, coarsest first, then the image grid's own sums, as
    :func:`~weathergen.engine.composite.planes` adds them); a coarse level is upsampled only for
    the frames and layers that draw on it (``used``: ``(level, t, k)``), and the image grid's
    sums, exact zeros where a frame and layer draws on coarse grids alone (fog), are then not
    added (adding +0 changes no bit: sums are never −0).

    The gradient (:meth:`gradient`, then :meth:`write` once per frame and layer) is allocated
    uninitialised: the image grid's A and C planes are written whole by :meth:`write`, and only
    its margins, its Z plane and the (small) coarse grids are zero-filled."""

    def __init__(self, grids, used: set, bsz: int, nl: int):
        self.grids, self.used, self.bsz, self.nl = grids, used, bsz, nl

    def _views(self, t: int, k: int) -> slice:
        n = self.bsz * self.nl
        return slice(t * n + k, (t + 1) * n, self.nl)

    def _levels(self, t: int, k: int):
        for index, (level, _, h, w, _) in enumerate(self.grids.levels):
            if level and (level, t, k) in self.used:
                yield index, level, h, w

    def read(self, values: torch.Tensor, t: int, k: int) -> torch.Tensor:
        """Shape: -> (5, B, H, W) (a view of the sums where no coarse level is used)."""
        grids, at = self.grids, self._views(t, k)
        total = None
        for index, level, h, w in self._levels(t, k):
            coarse = grids.planes(values, index)[:, at]                   # (5, B, h, w)
            up = upsample(coarse.reshape(-1, 1, h, w), 2 ** level, (grids.height, grids.width))
            up = up.view(coarse.shape[0], coarse.shape[1], grids.height, grids.width)
            total = up if total is None else total + up
        fine = grids.planes(values, len(grids.levels) - 1)[:, at]
        if total is None:
            return fine
        return total + fine if (0, t, k) in self.used else total

    def gradient(self, shape, dtype, device) -> torch.Tensor:
        """The sums' gradient before :meth:`write`: zeros but where every frame and layer's
        :meth:`write` copies its image-grid A and C planes."""
        out = torch.empty(shape, dtype=dtype, device=device)
        grids = self.grids
        for index, (_, offset, h, w, m) in enumerate(grids.levels):
            size = grids.views * (h + 1) * (w + 2 * m)
            if index < len(grids.levels) - 1:
                out[:, offset:offset + size].zero_()
                continue
            full = out[:, offset:offset + size].view(out.shape[0], grids.views, h + 1, w + 2 * m)
            full[..., h, :].zero_()
            full[..., :h, :m].zero_()
            full[..., :h, m + w:].zero_()
            full[4:, :, :h, m:m + w].zero_()
        return out

    def write(self, g_values: torch.Tensor, g_alpha: torch.Tensor, g_colour: torch.Tensor,
              t: int, k: int) -> None:
        """Add the gradients of :meth:`read`'s A (B, 1, H, W) and C (B, 3, H, W) planes into
        ``g_values`` (the depth sum Z passes none)."""
        grids, at = self.grids, self._views(t, k)
        fine = grids.planes(g_values, len(grids.levels) - 1)[:, at]
        fine[0].copy_(g_alpha[:, 0])
        fine[1:4].copy_(g_colour.transpose(0, 1))
        levels = list(self._levels(t, k))
        if not levels:
            return
        grad = torch.cat((g_alpha.transpose(0, 1), g_colour.transpose(0, 1)))  # (4, B, H, W)
        for index, level, h, w in levels:
            back = upsample_adjoint(grad.view(-1, 1, grids.height, grids.width), 2 ** level,
                                    (h, w))
            grids.planes(g_values, index)[:4, at].add_(back.view(*grad.shape[:2], h, w))


class _GridLayout:
    """Planes given whole, ``(5, T, B, L, 1, H, W)`` (:func:`composite_layers`)."""

    def gradient(self, shape, dtype, device) -> torch.Tensor:
        return torch.zeros(shape, dtype=dtype, device=device)

    def read(self, values: torch.Tensor, t: int, k: int) -> torch.Tensor:
        return values[:, t, :, k, 0]

    def write(self, g_values: torch.Tensor, g_alpha: torch.Tensor, g_colour: torch.Tensor,
              t: int, k: int) -> None:
        g_values[0, t, :, k].add_(g_alpha)
        g_values[1:4, t, :, k, 0].add_(g_colour.transpose(0, 1))


def composite_layers(alpha: torch.Tensor, colour: torch.Tensor, depth: torch.Tensor,
                     image: torch.Tensor, alpha_mode: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """The frames of layered sums: per pixel the layers far to near by their mean depth
    ``Z / A``, each blended over the result so far with its mode, clamped once at the end.

    Shape: alpha (B, L, 1, H, W) ``A``; colour (B, L, 3, H, W) ``C``; depth (B, L, 1, H, W)
    ``Z = Σ θ B V z``; image (B, 3, H, W); alpha_mode (B, L) bool -> (image (B, 3, H, W),
    opacity (B, 1, H, W)). Differentiable in alpha, colour and image (not in the order).
    """
    grid = torch.cat((alpha, colour, depth), 2).permute(2, 0, 1, 3, 4)[:, None, :, :, None]
    out, opacity = _LayeredBlend.apply(grid, alpha_mode, _GridLayout(), image)
    return out, opacity


class _LayeredBlend(torch.autograd.Function):
    """T frames of a batch of B pairs with L layers each, composited per pixel far to near.

    The order is a sorting network of compare-and-swap steps on whole frames (``L (L − 1) / 2``
    of them: one for two layers), each a few elementwise selections whose masks the backward
    pass replays (a layer that covers a pixel not at all blends nothing there, wherever it
    sorts). An additive layer blends as one of zero opacity: ``I (1 − 0) + C``. Layer
    ``k`` is nearer than layer ``j`` where ``Z_k A_j < Z_j A_k`` (mean depths compared without
    a division).

    Shape: values as ``layout`` reads them (the splat's flat sums, or whole planes), each frame
    and layer's planes (5, B, H, W) (A, C_r, C_g, C_b, Z); alpha_mode (B, L) bool; images T
    tensors (B, 3, H, W) -> T images (B, 3, H, W), then T opacities (B, 1, H, W). Gradients flow
    to the A and C planes (one allocation of the values' shape) and the images.
    """

    @staticmethod
    def forward(ctx, values, alpha_mode, layout, *images):
        nl = alpha_mode.shape[1]
        mode = alpha_mode.to(values.dtype)[:, :, None, None]                # (B, L, 1, 1)
        every = alpha_mode.all(0).tolist()      # layers alpha-blended in every pair: A as is
        grad = any(ctx.needs_input_grad)
        outs, opacities, saved = [], [], []
        for t, image in enumerate(images):
            planes = [layout.read(values, t, k) for k in range(nl)]         # (5, B, H, W) each
            alpha = [p[0].unsqueeze(1) for p in planes]                     # (B, 1, H, W)
            depth = [p[4].unsqueeze(1) for p in planes]
            cover = [alpha[k] if every[k] else alpha[k] * mode[:, k, None] for k in range(nl)]
            paint = [p[1:4].transpose(0, 1) for p in planes]                # (B, 3, H, W)
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
        ctx.shape, ctx.mode = values.shape, mode
        return (*outs, *opacities)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        frames = len(ctx.saved)
        g_values = ctx.layout.gradient(ctx.shape, ctx.mode.dtype, ctx.mode.device)
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
                    inside = (clear[k] > 0) & (clear[k] < 1)
                    g_alpha = g_alpha + g_op * others * inside
                ctx.layout.write(g_values, g_alpha, g_paint[k], t, k)
        return (g_values, None, None, *g_images)
