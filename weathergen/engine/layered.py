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
from .composite import RenderOutput, planes
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
                 detach_occlusion=detach_occlusion)
    grid = planes(sums).view(5, 2, bsz, nl, 1, height, width)
    alpha_mode = torch.tensor([[r.settings.blend == "alpha" for r in p.layers] for p in layered],
                              device=device)
    outs = [composite_layers(grid[0, t], grid[1:4, t, :, :, 0].permute(1, 2, 0, 3, 4),
                             grid[4, t], image, alpha_mode)
            for t, image in enumerate((image1, image2))]
    return RenderOutput(image1=outs[0][0], image2=outs[1][0], opacity1=outs[0][1],
                        opacity2=outs[1][1], reached=sums.reached.view(2, bsz, nl).any(2).any(0))


def composite_layers(alpha: torch.Tensor, colour: torch.Tensor, depth: torch.Tensor,
                     image: torch.Tensor, alpha_mode: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """The frames of layered sums: per pixel the layers far to near by their mean depth
    ``Z / A``, each blended over the result so far with its mode, clamped once at the end.

    Shape: alpha (B, L, 1, H, W) ``A``; colour (B, L, 3, H, W) ``C``; depth (B, L, 1, H, W)
    ``Z = Σ θ B V z``; image (B, 3, H, W); alpha_mode (B, L) bool -> (image (B, 3, H, W),
    opacity (B, 1, H, W)). Differentiable in alpha, colour and image (not in the order).
    """
    nl = alpha.shape[1]
    with torch.no_grad():
        covered = alpha > 0
        mean = torch.where(covered, depth / torch.where(covered, alpha, torch.ones_like(alpha)),
                           torch.zeros_like(alpha))
        order = torch.sort(mean, dim=1, descending=True, stable=True).indices   # far first
        mode = alpha_mode.to(alpha.dtype)[:, :, None, None, None].expand_as(alpha)
        mode = mode.gather(1, order)
    a = alpha.gather(1, order)
    c = colour.gather(1, order.expand_as(colour))
    out = image
    for k in range(nl):
        out = torch.addcmul(c[:, k], out, 1 - a[:, k] * mode[:, k])
    clear = (1 - alpha.clamp(0, 1)).prod(1)
    return out.clamp(0, 1), (1 - clear).clamp(0, 1)
