"""Combined weather in one pass: every layer of a :class:`~weathergen.engine.LayeredParticles`
drawn by the render core, then composited once, in depth order
(:func:`~weathergen.engine.rendering.composite.blend_layers`, where the blend modes live).

Each layer is drawn as a single render draws its record (:func:`_layer_sums`): the layer's
records of every pair of the batch, the pairs' two views, its own tracks, stamps (from its own
template library; every layer's built in one pass, :func:`_layer_stamps`) and splat, with its
own grid levels, so a layer's sums ``A = Σ θ B V`` and ``C = Σ γ θ B V`` are the bytes of its
records rendered alone (a fog layer drawn on a coarse grid alone gets no image-grid planes).
Each blur sample of an alpha-blended layer carries its camera depth ``z`` as a fourth colour
channel, so its planes hold a fifth sum ``Z = Σ θ B V z`` (a passive sum: no gradient flows
back to it), and ``Z / A`` is the layer's opacity-weighted mean depth at each pixel.

Alpha-blended layers are drawn first. An additive layer's particles (snow, rain, sparks) are
then dimmed, each in each frame, by the alpha layers in front of it (:func:`_dimmed`): its θ is
multiplied by ``T = Π_l (1 − clamp(A_l, 0, 1))`` over the alpha layers whose mean depth at the
middle of the particle's streak is nearer than the particle, so its light and opacity reach the
camera through the fog in front of it; where no alpha layer lies in front, ``T = 1`` and the
layer's sums keep their bytes. Dimmed additive layers need no depth sum: they blend last.
The composite then orders the alpha layers at each pixel by ``Z / A``, far to near, and adds
the additive layers' light on top (see :mod:`~weathergen.engine.rendering.composite`).

The approximation and its limits: an alpha layer is one surface per pixel, at its mean depth
there, so two alpha layers that interleave in depth at a pixel are seen one wholly in front of
the other; an additive particle is in front of or behind an alpha layer as a whole (at the
middle of its streak), and dimmed by that layer's opacity there over its whole stamp. The order
is a step function of the depths, so gradients flow through every layer's ``A`` and ``C`` and
through each dimming factor (to colours, offsets and transparencies), not through which layer
is in front. A pair rendered with one layer gives the bytes of its record rendered alone.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Optional, Sequence, Union

import torch

from ...errors import ConfigError
from .transmittance import Air, dimming, pair_air, through_air, view_air
from .composite import RenderOutput, blend_layers
from ..records.layered import LayeredParticles
from ..records.particles import Particles
from .planes import Sums, planes
from .splat import chunk_elements_for, splat
from .stamps import COARSE_SIDE, StampSet, build, build_many
from ..weather.templates import TemplateLibrary, load_templates
from .tracks import (Looks, ParticleTable, RecordRows, Tracks, blur_samples, empty_looks,
                     fixed_looks, pair_starts, pair_tracks, view_tracks)
from ..views import View, Views

__all__ = ["as_layers", "build_layer_stamps", "layers_view_sums", "render_layers",
           "render_layers_view"]


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
    part per template library, in the order the libraries are first named; record ``b`` is
    drawn into pair ``b``."""
    out = []
    for name, lib in libs.items():
        chosen = [q for q, r in enumerate(records) if r.settings.templates == name and r.count
                  and (r.optics is None) == paper]
        if chosen:
            looks, tracks = pair_tracks([records[q] for q in chosen], views, lib.resolution,
                                        beta=beta, dtype=dtype, pairs=chosen)
            out.append((looks, tracks, lib))
    return out


def _check_blends(records: Sequence[Particles]) -> None:
    for r in records:
        if r.settings.blend not in ("additive", "alpha"):
            raise ConfigError(f"unknown blend mode {r.settings.blend!r}")


def _flat(layered: Sequence[LayeredParticles]) -> list[Particles]:
    return [r for p in layered for r in p.layers]


def _stacks(layered: Sequence[LayeredParticles]) -> list[list[Particles]]:
    """Per layer, its record in every pair."""
    return [[p.layers[k] for p in layered] for k in range(len(layered[0].layers))]


def build_layer_stamps(particles: Union[LayeredParticles, Sequence[LayeredParticles]], *,
                       dtype: torch.dtype = torch.float32, device=None,
                       coarse_side: Optional[int] = COARSE_SIDE) -> StampSet:
    """The stamps of the layers' particles of the paper's model, in the order
    :func:`render_layers` draws them: layer after layer, each layer's in the order of its
    records (reusable across attack steps, as :func:`~weathergen.engine.build_stamps` for a
    single record)."""
    layered = as_layers(particles)
    records = _flat(layered)
    device = torch.device(device) if device is not None else records[0].device
    with torch.no_grad():
        parts = []
        for stack in _stacks(layered):
            for name, lib in _libraries(stack).items():
                chosen = [r.to(device) for r in stack if r.settings.templates == name and r.count
                          and r.optics is None]
                if chosen:
                    parts.append((fixed_looks(ParticleTable.of(chosen, device),
                                              RecordRows.of(chosen, device), lib.resolution),
                                  lib))
        if not parts:
            return build(empty_looks(device), next(iter(_libraries(records).values())),
                         dtype=dtype)
        return build_many(parts, dtype=dtype, coarse_side=coarse_side)


def _cut(stamps: StampSet, counts: Sequence[int]) -> list[StampSet]:
    """``stamps`` cut into consecutive sets of ``counts`` entries (each stamp's pixels follow
    the previous one's). One host synchronisation."""
    ends = [0, *itertools.accumulate(counts)]
    bounds = torch.cat((stamps.first, stamps.first.new_tensor([stamps.pixels.numel()])))
    at = bounds.index_select(0, torch.tensor(ends, device=bounds.device)).tolist()
    return [StampSet(pixels=stamps.pixels[at[k]:at[k + 1]], first=stamps.first[lo:hi] - at[k],
                     side=stamps.side[lo:hi], coarse=stamps.coarse[lo:hi],
                     phases=stamps.phases[lo:hi], gap=stamps.gap[lo:hi])
            for k, (lo, hi) in enumerate(zip(ends[:-1], ends[1:]))]


def _layer_parts(records: Sequence[Particles], views: Views, *, beta: float,
                 dtype) -> tuple[dict, list, list]:
    """One layer's template libraries and its parts (looks, tracks, library) as a single render
    draws its records: the paper's model's, then the fields'."""
    libs = _libraries(records)
    return (libs, _parts(records, views, libs, beta=beta, dtype=dtype, paper=True),
            _parts(records, views, libs, beta=beta, dtype=dtype, paper=False))


def _layer_stamps(prepared: Sequence[tuple], given: Sequence[Optional[StampSet]], *, dtype,
                  device, coarse_side: Optional[int], chunk_elements: int) -> list[StampSet]:
    """Every layer's stamps in the order of its parts (paper, then fields), the ones to build
    (a layer's paper-model stamps unless ``given``, and its fields') built in one call for all
    the layers (:func:`~weathergen.engine.rendering.stamps.build_many`: each stamp the bytes of its
    layer's own build)."""
    todo, counts = [], []
    for (_, paper, field), part in zip(prepared, given):
        mine = (paper if part is None else []) + field
        todo += [(looks, lib) for looks, _, lib in mine]
        counts.append(sum(looks.count for looks, _, _ in mine))
    built = _cut(build_many(todo, dtype=dtype, coarse_side=coarse_side,
                            chunk_elements=chunk_elements), counts) if todo \
        else [None] * len(prepared)
    out = []
    for (libs, paper, field), part, new in zip(prepared, given, built):
        pieces = ([part.to(dtype, device)] if part is not None and part.count else []) \
            + ([new] if new is not None and new.count else [])
        if not paper + field:
            out.append(build(empty_looks(device), next(iter(libs.values())), dtype=dtype))
        else:
            out.append(pieces[0] if len(pieces) == 1 else StampSet.cat(pieces))
    return out


def _layer_sums(views: Views, paper: list, field: list, stamp_set: StampSet, *, beta: float,
                dtype, chunk_elements: int, detach_occlusion: bool, depth: bool,
                dim, alpha: torch.Tensor, under: Sequence[Sums] = (), tint: bool = True) -> Sums:
    """One layer's sums on the pairs' views, drawn as a single render draws its records (the
    same tracks, stamps, grid levels and splat) from its parts (:func:`_layer_parts`) and
    stamps (:func:`_layer_stamps`); ``depth``: with the depth sum ``Z`` as a fifth (passive)
    plane; ``under``: the sums (with ``Z``) of the alpha-blended layers that dim this additive
    layer's particles (:func:`_dimmed`); ``dim``: the atmosphere between the particles and the
    cameras (:func:`~weathergen.engine.rendering.transmittance.dimming`; ``alpha`` (V,) which
    views draw this layer alpha-blended, ``tint`` as there)."""
    parts = paper + field
    if parts:
        offsets = [0]
        for looks, _, _ in parts[:-1]:
            offsets.append(offsets[-1] + looks.count)
        tracks = Tracks.cat([t for _, t, _ in parts], offsets)
    else:
        tracks = pair_tracks([], views, 1, beta=beta, dtype=dtype)[1]
    if under:
        tracks = _dimmed(tracks, under)
    tracks = dim(tracks, alpha, tint=tint)
    inst = blur_samples(tracks, dtype, stamp_set.gap)
    if depth:
        inst = dataclasses.replace(inst, color=torch.cat((inst.color, inst.z.detach()[:, None]),
                                                         1))
    return splat(inst, stamp_set, views.depth, chunk_elements=chunk_elements,
                 detach_occlusion=detach_occlusion, passive=int(depth), depth_aware=False)


def _dimmed(tracks: Tracks, alpha_layers: Sequence[Sums]) -> Tracks:
    """An additive layer's tracks, each particle's θ in each view times the share of its light
    that passes the alpha-blended layers in front of it: ``T = Π_l (1 − clamp(A_l, 0, 1))``
    over the alpha layers ``l`` whose mean depth ``Z_l / A_l`` is nearer than the particle,
    both read at the middle of its streak (:func:`_read_sums`). ``T`` is exactly 1 (and θ keeps
    its bits) where no alpha layer lies in front. Differentiable in the alpha layers' ``A`` and
    the streak's position (not in which layer is in front: a step of the depths)."""
    if tracks.count == 0:
        return tracks
    reach = (tracks.samples - 1).clamp(min=0) * tracks.spacing
    middle = torch.addcmul(tracks.h0, (0.5 * reach)[:, None], tracks.hd)
    z = middle[:, 2]
    safe = torch.where(z.abs() > 1e-12, z, 1e-12)
    dtype = tracks.theta.dtype
    u, v = (middle[:, 0] / safe).to(dtype), (middle[:, 1] / safe).to(dtype)
    near = z.detach().to(dtype)
    passed = None
    for sums in alpha_layers:
        alpha, depth = _read_sums(sums, tracks.view, u, v)
        dim = 1 - torch.where(depth < near * alpha, alpha.clamp(0, 1), 0)
        passed = dim if passed is None else passed * dim
    return dataclasses.replace(tracks, theta=tracks.theta * passed)


def _read_sums(sums: Sums, view: torch.Tensor, u: torch.Tensor, v: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """A layer's opacity sum ``A`` and depth sum ``Z`` (detached) at image points ``(u, v)`` of
    views ``view``, as its planes on the image grid hold them (each grid level interpolated
    bilinearly at ``(u + 0.5) / f − 0.5``, edges replicated: what
    :func:`~weathergen.engine.rendering.planes.upsample` gives at pixel centres).
    Shape: view, u, v (T,) -> two (T,)."""
    grids = sums.grids
    a_total = z_total = None
    for level, offset, h, w, m in grids.levels:
        f = 2 ** level
        x, y = ((u + 0.5) / f - 0.5, (v + 0.5) / f - 0.5) if level else (u, v)
        x, y = x.clamp(0, w - 1), y.clamp(0, h - 1)
        x0, y0 = torch.floor(x.detach()).long(), torch.floor(y.detach()).long()
        fx, fy = x - x0, y - y0
        x1, y1 = (x0 + 1).clamp_(max=w - 1), (y0 + 1).clamp_(max=h - 1)
        row_len = w + 2 * m
        base = offset + m + view * ((h + 1) * row_len)
        rows = torch.stack((base + y0 * row_len, base + y1 * row_len))         # (2, T)
        at = torch.stack((rows + x0, rows + x1), 1).view(-1)                   # (2 y, 2 x, T)
        n = u.numel()
        corners_a = sums.values[0].index_select(0, at).view(2, 2, n)
        corners_z = sums.values[-1].detach().index_select(0, at).view(2, 2, n)
        a, z = (torch.lerp(torch.lerp(c[0, 0], c[0, 1], fx), torch.lerp(c[1, 0], c[1, 1], fx),
                           fy) for c in (corners_a, corners_z))
        a_total = a if a_total is None else a_total + a
        z_total = z if z_total is None else z_total + z
    return a_total, z_total.detach()


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
    bsz = image1.shape[0]
    device = image1.device
    _check_blends(_flat(layered))
    stacks = _stacks(layered)
    alpha_mode = torch.tensor([[r.settings.blend == "alpha" for r in p.layers] for p in layered],
                              device=device)
    modes = [{r.settings.blend for r in stack} for stack in stacks]
    views = Views.of(torch.cat((intrinsics, intrinsics)).to(device),
                     torch.cat((cam1_from_ref, cam2_from_ref)).to(device),
                     torch.cat((depth1, depth2)), device=device)
    if chunk_elements is None:
        chunk_elements = chunk_elements_for(device)
    counts = [sum(r.count for r in stack if r.optics is None) for stack in stacks]
    if stamps is not None and stamps.count != sum(counts):
        raise ConfigError(f"stamps hold {stamps.count} entries but the layers hold {sum(counts)} "
                          f"particles of the paper's model (build them from these layers)")
    cut = _cut(stamps, counts) if stamps is not None else [None] * len(stacks)
    prepared = [_layer_parts(stack, views, beta=float(beta), dtype=image1.dtype)
                for stack in stacks]
    stamp_sets = _layer_stamps(prepared, cut, dtype=image1.dtype, device=device,
                               coarse_side=coarse_side, chunk_elements=chunk_elements)
    air = pair_air(layered, intrinsics, cam1_from_ref, cam2_from_ref, image1.shape[-2:], device)
    (out1, out2), (opacity1, opacity2), reached = _draw(
        views, prepared, stamp_sets, modes, alpha_mode, (image1, image2), beta=float(beta),
        chunk_elements=chunk_elements, detach_occlusion=detach_occlusion, air=air)
    return RenderOutput(image1=out1, image2=out2, opacity1=opacity1, opacity2=opacity2,
                        reached=reached.view(2, bsz).any(0))


def render_layers_view(image: torch.Tensor, view: View, particles: LayeredParticles, *,
                       frame: int = 0, beta: float, chunk_elements: Optional[int] = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """One weather frame of combined weather seen by ``view``: every layer's particles from
    their reference positions in frame ``frame`` + 1 (``P + δ1``, or ``P + δ1 + M + δ2`` for
    frame 2; along ``M + δ2``), each layer drawn as :func:`~weathergen.engine.render_view`
    draws its record, composited as :func:`render_layers` does. For weather fields, frame 1 is
    the bytes of frame 1 of a pair whose first view is ``view`` (a sequence writes each frame
    once). Shape: image (3, H, W) -> (image (3, H, W), opacity (1, H, W))."""
    views, prepared, stamp_sets, chunk_elements, modes, alpha_mode, air = _view_parts(
        view, particles, None, frame=frame, beta=beta, dtype=image.dtype, device=image.device,
        chunk_elements=chunk_elements)
    (out,), (opacity,), _ = _draw(views, prepared, stamp_sets, modes, alpha_mode, (image[None],),
                                  beta=float(beta), chunk_elements=chunk_elements,
                                  detach_occlusion=False, air=air)
    return out[0], opacity[0]


def layers_view_sums(view: View, particles: LayeredParticles,
                     values: Sequence[Optional[torch.Tensor]], *, beta: float, dtype, device,
                     chunk_elements: Optional[int] = None) -> list[tuple[torch.Tensor,
                                                                         torch.Tensor]]:
    """Every layer's sums in frame 1 seen by ``view``, as :func:`render_layers_view` draws them
    (the additive layers' particles dimmed by the alpha layers in front of them), with
    ``values[l]`` (N_l, 3) in place of layer ``l``'s colours where given (e.g. flow vectors).
    Shape: -> per layer (A (1, H, W), C (3, H, W))."""
    views, prepared, stamp_sets, chunk_elements, modes, alpha_mode, air = _view_parts(
        view, particles, values, frame=0, beta=beta, dtype=dtype, device=device,
        chunk_elements=chunk_elements)
    sums = _layer_sums_all(views, prepared, stamp_sets, modes, beta=float(beta), dtype=dtype,
                           chunk_elements=chunk_elements, detach_occlusion=False,
                           dim=dimming(air), alpha_mode=alpha_mode, tint=False)
    out = []
    for s in sums:
        grid = planes(s)[:, 0, 0]
        out.append((grid[:1], grid[1:4]))
    return out


def _view_parts(view: View, particles: LayeredParticles, values, *, frame: int, beta: float,
                dtype, device, chunk_elements: Optional[int]):
    """What one view draws of every layer: (views, prepared parts, stamps, chunk size, blend
    modes, which layers blend alpha (1, L), the air), each layer's tracks from
    :func:`~weathergen.engine.rendering.tracks.view_tracks`."""
    layered = as_layers(particles)[0]
    device = torch.device(device)
    _check_blends(layered.layers)
    views = Views.of(view.intrinsics[None].to(device), view.cam_from_ref[None].to(device),
                     view.depth[None].to(device), device=device)
    prepared = []
    for k, record in enumerate(layered.layers):
        libs = _libraries([record])
        lib = libs[record.settings.templates]
        record = record.to(device)
        start1, start2, displacement = pair_starts(record, torch.float64, device)
        start = start2 if frame else start1
        colour = None if values is None else values[k]
        looks, tracks = view_tracks(record, views, start, displacement, lib.resolution,
                                    beta=float(beta), dtype=dtype, color=colour)
        part = [(looks, tracks, lib)] if record.count else []
        prepared.append((libs, part if record.optics is None else [],
                         part if record.optics is not None else []))
    if chunk_elements is None:
        chunk_elements = chunk_elements_for(device)
    stamp_sets = _layer_stamps(prepared, [None] * len(prepared), dtype=dtype, device=device,
                               coarse_side=COARSE_SIDE, chunk_elements=chunk_elements)
    alpha_mode = torch.tensor([[r.settings.blend == "alpha" for r in layered.layers]],
                              device=device)
    return (views, prepared, stamp_sets, chunk_elements, [{r.settings.blend} for r in layered.layers],
            alpha_mode, view_air(layered, view, frame, device))


def _layer_sums_all(views: Views, prepared: list, stamp_sets: list, modes: list, *,
                    beta: float, dtype, chunk_elements: int, detach_occlusion: bool,
                    dim, alpha_mode: torch.Tensor, tint: bool = True) -> list:
    """Every layer's :class:`Sums`: the alpha-blended layers first (with their depth sums),
    then the additive layers, whose particles behind them they dim (:func:`_dimmed`; those
    carry no depth sum: they blend as the nearest). Two additive layers carry none either.
    With ``dim``, every layer's particles are seen through the air (``alpha_mode`` (B, L): which
    layer blends alpha in which pair)."""
    additive_pair = modes == [{"additive"}, {"additive"}]
    additive = [m == {"additive"} for m in modes]
    dimming = any(additive) and not all(additive)
    sums: list = [None] * len(modes)
    for k in sorted(range(len(modes)), key=lambda k: additive[k] if dimming else 0):
        (_, paper, field), stamp_set = prepared[k], stamp_sets[k]
        under = [sums[j] for j in range(len(modes)) if not additive[j]] \
            if dimming and additive[k] else ()
        alpha = alpha_mode[:, k].repeat(views.count // alpha_mode.shape[0])
        sums[k] = _layer_sums(views, paper, field, stamp_set, beta=beta, dtype=dtype,
                              chunk_elements=chunk_elements, detach_occlusion=detach_occlusion,
                              depth=not additive_pair and not under, under=under, dim=dim,
                              alpha=alpha, tint=tint)
    return sums


def _draw(views: Views, prepared: list, stamp_sets: list, modes: list, alpha_mode: torch.Tensor,
          images: tuple, *, beta: float, chunk_elements: int, detach_occlusion: bool,
          air: Optional[Air] = None) -> tuple[list, list, torch.Tensor]:
    """Every layer's sums on ``views`` and the composite of ``images`` (T frames of B views
    each, frame ``t``'s views ``t B .. t B + B − 1``), seen through ``air``
    (:func:`~weathergen.engine.rendering.transmittance.through_air`): the frames, their
    opacities, and which views any layer (or the air) reached (V,)."""

    def draw(dim):
        sums = _layer_sums_all(views, prepared, stamp_sets, modes, beta=beta,
                               dtype=images[0].dtype, chunk_elements=chunk_elements,
                               detach_occlusion=detach_occlusion, dim=dim, alpha_mode=alpha_mode)

        def blend(seen):
            outs = blend_layers(sums, modes, alpha_mode, seen)
            return outs[:len(seen)], outs[len(seen):], torch.stack([s.reached for s in sums]).any(0)
        return blend

    return through_air(air, views.depth, images, draw)
