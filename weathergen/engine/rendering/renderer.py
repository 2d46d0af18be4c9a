"""The particle renderer's public entry points: frames and particle records in, weather frames out.

Pure functions, tensors in and tensors out, no file I/O; device-agnostic (every tensor follows the
images' device). Every entry point runs the one render core, four stages with a typed record
between each (see ``docs/engine.md``):

1. :mod:`~weathergen.engine.rendering.tracks`: records and cameras -> :class:`~weathergen.engine.rendering.tracks.Looks`
   (one row per stamp entry) and :class:`~weathergen.engine.rendering.tracks.Tracks` (an entry's streak in
   one view), then :class:`~weathergen.engine.rendering.tracks.Instances` (the blur samples);
2. :mod:`~weathergen.engine.rendering.stamps`: looks -> :class:`~weathergen.engine.rendering.stamps.StampSet`;
3. :mod:`~weathergen.engine.rendering.splat`: samples and stamps -> :class:`~weathergen.engine.rendering.splat.Sums`
   (``A = Σ θ B V``, ``C = Σ γ θ B V`` per view), differentiably;
4. :mod:`~weathergen.engine.rendering.planes`, then :mod:`~weathergen.engine.rendering.composite`: sums -> planes on
   the image grid -> frames and opacities (:class:`RenderOutput`); the blend modes, a single
   record's and combined weather's layers (drawn by :mod:`~weathergen.engine.rendering.combined`), all
   live in :mod:`~weathergen.engine.rendering.composite`.

Both weather models go through the same stages: a record of the paper's model carries its looks,
a record sampled from a weather field (``optics`` set) gets its looks per view in stage 1.
Gradients flow to ``offset1``, ``offset2`` (through the projected positions and, unless
``detach_occlusion``, the particle depth in the visibility ``V``), ``color`` and
``transparency``; use ``beta=BETA_ATTACK`` when differentiating through occlusion. On the CPU a
pair's frames are the same bytes whatever other pairs the call holds; on CUDA the splat's atomic
additions may change the last bits between runs.
"""

from __future__ import annotations

from typing import Optional, Sequence, Union

import torch

from ...errors import ConfigError, DatasetError, ShapeError
from ...framepair import FramePair, FramePairBatch
from ..common import check_pair_for_engine, reference_transforms, resolve_device
from .transmittance import dimming, pair_air, through_air, view_air
from .composite import RenderOutput, composite, composite_in_order
from .combined import as_layers, build_layer_stamps, render_layers, render_layers_view
from ..records.layered import LayeredParticles
from ..records.particles import Particles
from .planes import planes
from ..weather.presets import BLEND_MODES
from .splat import SPLAT_CHUNK_ELEMENTS, chunk_elements_for, splat
from .stamps import COARSE_SIDE, StampSet, build, stored
from ..weather.templates import TemplateLibrary, load_templates
from .tracks import (ParticleTable, RecordRows, blur_samples, empty_looks, fixed_looks,
                     pair_starts, pair_tracks, view_tracks)
from ..views import View, Views

BETA_RENDER = 250.0
BETA_ATTACK = 30.0
#: Patch pixels per chunk of the splat on the CPU (memory is bounded by the chunk size).
DEFAULT_CHUNK_ELEMENTS = SPLAT_CHUNK_ELEMENTS

__all__ = ["BETA_ATTACK", "BETA_RENDER", "DEFAULT_CHUNK_ELEMENTS", "RenderOutput", "StampSet",
           "build_stamps", "check_records", "pair_starts", "render", "render_first_frame",
           "render_pair", "render_view", "view_sums"]


def check_records(records: Sequence[Particles],
                  templates: Optional[TemplateLibrary] = None) -> TemplateLibrary:
    """The template library the records of one render call are drawn with (``templates``, or
    the one their settings name), after checking that they share it, that it is the library
    they were sampled with, and their blend modes. Raises ConfigError."""
    if templates is None:
        names = {r.settings.templates for r in records}
        if len(names) != 1:
            raise ConfigError(f"records of one render call must share templates; got {sorted(names)}")
        templates = load_templates(names.pop())
    for r in records:
        if r.stamps is not None:
            check_stored_stamps(r)
            continue            # drawn with its own stamps: the library is not read
        if r.settings.templates_digest and templates.digest != r.settings.templates_digest:
            raise ConfigError(f"particles were sampled with templates '{r.settings.templates}' "
                              f"(digest {r.settings.templates_digest}) but are rendered with "
                              f"'{templates.name}' (digest {templates.digest})")
        if r.settings.blend not in BLEND_MODES:
            raise ConfigError(f"unknown blend mode {r.settings.blend!r}")
    return templates


def check_stored_stamps(record: Particles) -> None:
    """A record's stored stamps must be one odd square per particle of the paper's model."""
    stamps = record.stamps
    if record.optics is not None:
        raise ConfigError("stored stamps belong to particles of the paper's model (no optics)")
    if (stamps.dim() != 3 or stamps.shape[0] != record.count or stamps.shape[1] != stamps.shape[2]
            or stamps.shape[-1] % 2 == 0):
        raise ConfigError(f"stored stamps must be (N, S, S), S odd, for N = {record.count} "
                          f"particles; got {tuple(stamps.shape)}")


def paper_stamps(records: Sequence[Particles], looks, templates: TemplateLibrary, *,
                 dtype: torch.dtype, coarse_side: Optional[int],
                 chunk_elements: int = DEFAULT_CHUNK_ELEMENTS) -> StampSet:
    """The stamps of the paper-model entries of ``looks`` (the records' particles, in record
    order): rasterised from the library, or a record's stored stamps where it has them."""
    paper = [r for r in records if r.optics is None and r.count]
    if not any(r.stamps is not None for r in paper):
        return build(looks, templates, dtype=dtype, coarse_side=coarse_side,
                     chunk_elements=chunk_elements)
    parts, at, run = [], 0, 0
    device = looks.template.device

    def flush(start, stop):
        if stop > start:
            parts.append(build(looks.select(torch.arange(start, stop, device=device)), templates,
                               dtype=dtype, coarse_side=coarse_side, chunk_elements=chunk_elements))

    for r in paper:
        if r.stamps is not None:
            flush(run, at)
            parts.append(stored(r.stamps, dtype=dtype, device=device))
            run = at + r.count
        at += r.count
    flush(run, at)
    return StampSet.cat(parts)


def build_stamps(records: Sequence[Particles], templates: TemplateLibrary, *,
                 dtype: torch.dtype = torch.float32, device=None,
                 coarse_side: Optional[int] = COARSE_SIDE) -> StampSet:
    """The stamps of the records' particles of the paper's model, one entry per particle in
    record order (weather-field records have none: their looks change with every view). Reusable
    by :func:`render` while scale, rotation, template and defocus stay fixed (e.g. across attack
    steps). ``coarse_side``: stamps at least this wide are drawn for a coarser grid (``None``:
    every stamp at full resolution). Combined weather (:class:`LayeredParticles` of several
    layers): the layers' stamps, each from its own library (``templates`` is not used)."""
    if isinstance(records, LayeredParticles) or any(isinstance(r, LayeredParticles)
                                                    for r in records):
        layered = as_layers(records)
        if len(layered[0].layers) > 1:
            return build_layer_stamps(layered, dtype=dtype, device=device,
                                      coarse_side=coarse_side)
        records = [p.layers[0] for p in layered]
    device = torch.device(device) if device is not None else records[0].device
    paper = [r for r in records if r.optics is None and r.count]
    with torch.no_grad():
        if paper:
            looks = fixed_looks(ParticleTable.of(paper, device), RecordRows.of(paper, device),
                                templates.resolution)
            return paper_stamps(paper, looks, templates, dtype=dtype, coarse_side=coarse_side)
        return build(empty_looks(device), templates, dtype=dtype, coarse_side=coarse_side)


def render(image1: torch.Tensor, image2: torch.Tensor, depth1: torch.Tensor,
           depth2: torch.Tensor, intrinsics: torch.Tensor, cam1_from_ref: torch.Tensor,
           cam2_from_ref: torch.Tensor,
           particles: Union[Particles, LayeredParticles, Sequence[Particles | LayeredParticles]],
           templates: Optional[TemplateLibrary] = None, *, beta: float = BETA_RENDER,
           stamps: Optional[StampSet] = None, chunk_elements: Optional[int] = None,
           coarse_side: Optional[int] = COARSE_SIDE,
           detach_occlusion: bool = False) -> RenderOutput:
    """Render particle records into a batch of frame pairs, one record per pair.

    Shape:
        image1, image2: (B, 3, H, W) float in [0, 1]; depth1, depth2: (B, 1, H, W) camera-z.
        intrinsics: (B, 3, 3); cam1_from_ref, cam2_from_ref: (B, 4, 4), the cameras' transforms
            from each record's reference frame (see :func:`reference_transforms`).
        particles: one record per pair (a single record for B = 1), of either weather model, or
            one :class:`LayeredParticles` per pair (combined weather, the same number of layers
            each): drawn in one pass and composited in depth order
            (:mod:`~weathergen.engine.rendering.combined`; ``templates`` must then be None).
    Computes in the images' dtype and device. Returns :class:`RenderOutput`.
    ``stamps``: from :func:`build_stamps` of the same records (their paper-model particles).
    ``coarse_side``: stamps at least this wide are splatted on a coarser grid and upsampled;
    ``None`` renders every stamp at full resolution (ignored for ``stamps`` given).
    ``chunk_elements``: elements (patch pixels, stamp samples) per chunk of the stamps and the
    splat (default: by device, :func:`~weathergen.engine.rendering.splat.chunk_elements_for`).
    ``detach_occlusion``: no gradient through the visibility term (the particle depth in V).
    """
    records = _record_list(particles)
    _check_batch(image1, image2, depth1, depth2, len(records))
    dtype, device = image1.dtype, image1.device
    if any(isinstance(r, LayeredParticles) for r in records):
        layered = as_layers(records)
        if len(layered[0].layers) > 1:
            if templates is not None:
                raise ConfigError("combined weather is drawn with each layer's own templates; "
                                  "pass templates=None")
            return render_layers(image1, image2, depth1, depth2, intrinsics, cam1_from_ref,
                                 cam2_from_ref, layered, beta=beta, stamps=stamps,
                                 chunk_elements=chunk_elements, coarse_side=coarse_side,
                                 detach_occlusion=detach_occlusion)
        records = [p.layers[0] for p in layered]    # one layer: the record's own bytes
    templates = check_records(records, templates)
    depth = torch.cat((depth1, depth2)).detach().to(device)
    views = Views.of(torch.cat((intrinsics, intrinsics)).to(device),
                     torch.cat((cam1_from_ref, cam2_from_ref)).to(device),
                     depth_seen(depth, [r.settings.depth_shift for r in records] * 2),
                     device=device)
    looks, tracks = pair_tracks(records, views, templates.resolution, beta=float(beta),
                                dtype=dtype)
    air = pair_air(records, intrinsics, cam1_from_ref, cam2_from_ref, image1.shape[-2:], device)
    alpha_mode = torch.tensor([r.settings.blend == "alpha" for r in records], device=device)
    if chunk_elements is None:
        chunk_elements = chunk_elements_for(device)
    def draw(dim):
        seen = dim(tracks, torch.cat((alpha_mode, alpha_mode)))
        stamp_set = _entry_stamps(records, looks, templates, stamps, dtype=dtype,
                                  coarse_side=coarse_side, chunk_elements=chunk_elements)
        return _blender(records, seen, stamp_set, views.depth, alpha_mode, dtype=dtype,
                        chunk_elements=chunk_elements, detach_occlusion=detach_occlusion)
    frames, opacities, reached = through_air(air, depth, [image1, image2], draw)
    return RenderOutput(*frames, *opacities, reached=reached.view(2, -1).any(0))


def depth_seen(depth: torch.Tensor, shifts: Sequence[float]) -> torch.Tensor:
    """The scene depth that particles are tested against: each view's depth read its record's
    ``depth_shift`` s pixels up and left of each pixel, bilinearly, the image's first row and
    column repeated beyond it (s = 0.5: the mean of a pixel and its three upper-left
    neighbours). Shape: depth (V, 1, H, W), shifts V floats -> (V, 1, H, W)."""
    if not any(shifts):
        return depth
    s = torch.tensor(shifts, dtype=depth.dtype, device=depth.device).view(-1, 1, 1, 1)
    padded = torch.nn.functional.pad(depth, (1, 0, 1, 0), mode="replicate")
    up, left, corner = padded[..., :-1, 1:], padded[..., 1:, :-1], padded[..., :-1, :-1]
    return (1 - s) ** 2 * depth + s * (1 - s) * (up + left) + s * s * corner


def _check_batch(image1: torch.Tensor, image2: torch.Tensor, depth1: Optional[torch.Tensor],
                 depth2: Optional[torch.Tensor], records: int) -> None:
    """Check that :func:`render`'s frames are B pairs of one shape, with depth, and that there
    are B ``records``. Raises ShapeError, DatasetError (no depth) or ConfigError."""
    if image1.dim() != 4 or image1.shape[1] != 3 or image2.shape != image1.shape:
        raise ShapeError(f"images must be (B, 3, H, W) and equal; got {tuple(image1.shape)} "
                         f"and {tuple(image2.shape)}")
    bsz, _, height, width = image1.shape
    for name, d in (("depth1", depth1), ("depth2", depth2)):
        if d is None:
            raise DatasetError(f"{name} is missing; weather rendering needs scene depth")
        if tuple(d.shape) != (bsz, 1, height, width):
            raise ShapeError(f"{name} has shape {tuple(d.shape)}, expected "
                             f"{(bsz, 1, height, width)}")
    if records != bsz:
        raise ConfigError(f"{records} particle records for a batch of {bsz} frame pairs")


def _record_list(particles) -> list:
    """The records of a render call: one record (or layered record) alone, or a sequence."""
    return [particles] if isinstance(particles, (Particles, LayeredParticles)) \
        else list(particles)


def _entry_stamps(records: Sequence[Particles], looks, templates: TemplateLibrary,
                  stamps: Optional[StampSet], *, dtype: torch.dtype, coarse_side: Optional[int],
                  chunk_elements: int) -> StampSet:
    """The stamps of every entry of ``looks`` (:func:`pair_tracks` of ``records``): first the
    paper-model particles' (``stamps`` where given, else built from the library or a record's
    stored stamps), then the field particles' entries, built. Raises ConfigError when
    ``stamps`` do not hold one entry per paper-model particle."""
    device = looks.template.device
    paper = sum(r.count for r in records if r.optics is None)
    if stamps is not None:
        if stamps.count != paper:
            raise ConfigError(f"stamps hold {stamps.count} entries but the records hold {paper} "
                              f"particles of the paper's model (build them from these records)")
        rest = looks.select(torch.arange(paper, looks.count, device=device))
        return StampSet.cat([stamps.to(dtype, device),
                             build(rest, templates, dtype=dtype, coarse_side=coarse_side,
                                   chunk_elements=chunk_elements)])
    stamp_set = paper_stamps(records, looks.select(torch.arange(paper, device=device)),
                             templates, dtype=dtype, coarse_side=coarse_side,
                             chunk_elements=chunk_elements) \
        if any(r.stamps is not None for r in records) else \
        build(looks, templates, dtype=dtype, coarse_side=coarse_side,
              chunk_elements=chunk_elements)
    if stamp_set.count != looks.count:          # the field particles' entries after them
        stamp_set = StampSet.cat([stamp_set, build(
            looks.select(torch.arange(paper, looks.count, device=device)), templates,
            dtype=dtype, coarse_side=coarse_side, chunk_elements=chunk_elements)])
    return stamp_set


def _blender(records: Sequence[Particles], tracks, stamp_set: StampSet, depth: torch.Tensor,
             alpha_mode: torch.Tensor, *, dtype: torch.dtype, chunk_elements: int,
             detach_occlusion: bool):
    """How the splatted tracks are blended into the frames: a function of the two frames
    (B, 3, H, W) returning ``(frames, opacities, reached)`` (``reached`` (2 B,) per view).
    Records marked to blend their blur samples one after another (the research code's order,
    ``blends_in_order``) go through :func:`composite_in_order`; otherwise the splat's sums are
    blended at once (:func:`composite`). ``depth`` (2 B, 1, H, W): the views' scene depth."""
    in_order = [r.settings.blends_in_order for r in records]
    if any(in_order):
        marked = torch.tensor(in_order)
        return lambda images: composite_in_order(
            tracks, stamp_set, depth, images, alpha_mode, marked,
            chunk_elements=chunk_elements, detach_occlusion=detach_occlusion)
    sums = splat(blur_samples(tracks, dtype, stamp_set.gap), stamp_set, depth,
                 chunk_elements=chunk_elements, detach_occlusion=detach_occlusion)
    return lambda images: (*composite(sums, images, alpha_mode), sums.reached)


def render_pair(pair: Union[FramePair, FramePairBatch],
                particles: Union[Particles, LayeredParticles,
                                 Sequence[Particles | LayeredParticles]],
                templates: Optional[TemplateLibrary] = None, *, beta: float = BETA_RENDER,
                device=None, stamps: Optional[StampSet] = None,
                coarse_side: Optional[int] = COARSE_SIDE,
                detach_occlusion: bool = False) -> RenderOutput:
    """Render particles into a :class:`FramePair` (B = 1) or a :class:`FramePairBatch`.

    Picks each record's reference transforms from the pair's poses; raises ConfigError when a
    record sampled in world coordinates meets a pair without absolute poses.
    Shape: returns images (B, 3, H, W) and opacities (B, 1, H, W).
    """
    dev = resolve_device(device) if device is not None else None
    if isinstance(pair, FramePair):
        check_pair_for_engine(pair)
        if dev is not None:
            pair = pair.to(dev)
        frame, c1, c2 = reference_transforms(pair)
        records = _record_list(particles)
        fields = dict(image1=pair.image1[None], image2=pair.image2[None],
                      depth1=pair.depth1[None], depth2=pair.depth2[None],
                      intrinsics=pair.intrinsics[None])
        frames, c1, c2 = [frame], c1[None], c2[None]
    else:
        if pair.depth1 is None or pair.depth2 is None:
            raise DatasetError("frame-pair batch has no depth; weather rendering needs depth")
        world = pair.cam1_from_world is not None and pair.cam2_from_world is not None
        bsz = pair.image1.shape[0]
        if world:
            c1, c2, frames = pair.cam1_from_world, pair.cam2_from_world, ["world"] * bsz
        else:
            c1 = torch.eye(4, dtype=torch.float64).expand(bsz, 4, 4)
            c2, frames = pair.cam2_from_cam1, ["camera1"] * bsz
        records = _record_list(particles)
        fields = dict(image1=pair.image1, image2=pair.image2, depth1=pair.depth1,
                      depth2=pair.depth2, intrinsics=pair.intrinsics)
        if dev is not None:
            fields = {k: v.to(dev) for k, v in fields.items()}
    for rec, frame in zip(records, frames):
        if rec.frame != frame:
            raise ConfigError(f"particles live in {rec.frame} coordinates but the frame pair "
                              f"offers {frame} coordinates (sample them for this pair)")
    if dev is not None:
        records = [r.to(dev) for r in records]
    return render(**fields, cam1_from_ref=c1, cam2_from_ref=c2, particles=records,
                  templates=templates, beta=beta, stamps=stamps, coarse_side=coarse_side,
                  detach_occlusion=detach_occlusion)


# -- single views: a frame of a sequence, a second camera, ground truth ------------------------

def _view_sums(view: View, record: Particles, start: torch.Tensor, displacement: torch.Tensor,
               templates: TemplateLibrary, dim, *, beta: float, dtype, device,
               chunk_elements: Optional[int], values: Optional[torch.Tensor] = None,
               detach_occlusion: bool = False):
    """One view's splat sums (or, for a record blended in order, its tracks, stamps and depth),
    the tracks seen through ``dim`` (:func:`~weathergen.engine.rendering.transmittance.dimming`)."""
    views = Views.of(view.intrinsics[None], view.cam_from_ref[None],
                     depth_seen(view.depth[None].detach().to(device),
                                [record.settings.depth_shift]), device=device)
    looks, tracks, kept = view_tracks(record.to(device), views, start, displacement,
                                      templates.resolution, beta=float(beta), dtype=dtype,
                                      color=values, kept=True)
    # (with values in place of colours, only θ is dimmed)
    alpha = torch.tensor([record.settings.blend == "alpha"], device=device)
    tracks = dim(tracks, alpha, tint=values is None)
    if chunk_elements is None:
        chunk_elements = chunk_elements_for(torch.device(device))
    if record.stamps is not None:       # the particles in front of the camera, their own stamps
        check_stored_stamps(record)
        stamps = stored(record.stamps.to(device)[kept], dtype=dtype, device=device)
    else:
        stamps = build(looks, templates, dtype=dtype, chunk_elements=chunk_elements)
    if values is None and record.settings.blends_in_order:   # (render_view blends them in order)
        return tracks, stamps, views.depth
    return splat(blur_samples(tracks, dtype, stamps.gap), stamps, views.depth,
                 chunk_elements=chunk_elements, detach_occlusion=detach_occlusion)


def render_view(image: torch.Tensor, view: View, record: Particles, start: torch.Tensor,
                displacement: torch.Tensor, templates: TemplateLibrary, *,
                beta: float = BETA_RENDER, chunk_elements: Optional[int] = None,
                detach_occlusion: bool = False, frame: int = 0
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """One weather frame seen by ``view``: every particle from ``start`` (N, 3) along
    ``displacement`` (N, 3), reference frame (a field record with the view's looks), and the
    record's atmosphere as in frame ``frame`` (0 or 1) of its pair. The same bytes as the frame
    of a pair that holds this view. ``detach_occlusion`` as for :func:`render`.

    Shape: image (3, H, W) -> (image (3, H, W), opacity (1, H, W)).
    """
    alpha_mode = torch.tensor([record.settings.blend == "alpha"], device=image.device)

    def draw(dim):
        sums = _view_sums(view, record, start, displacement, templates, dim, beta=beta,
                          dtype=image.dtype, device=image.device, chunk_elements=chunk_elements,
                          detach_occlusion=detach_occlusion)
        if isinstance(sums, tuple):
            return lambda images: composite_in_order(
                *sums, images, alpha_mode, torch.ones(1, dtype=torch.bool),
                chunk_elements=chunk_elements, detach_occlusion=detach_occlusion)
        return lambda images: (*composite(sums, images, alpha_mode), None)

    air = view_air(record, view, frame, image.device)
    (out,), (opacity,), _ = through_air(air, view.depth[None].to(image.device), [image[None]],
                                        draw)
    return out[0], opacity[0]


def view_sums(view: View, record: Particles, start: torch.Tensor, displacement: torch.Tensor,
              templates: TemplateLibrary, *, beta: float = BETA_RENDER,
              values: Optional[torch.Tensor] = None, dtype=torch.float64, device=None,
              chunk_elements: Optional[int] = None, frame: int = 0
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The splat's sums of one view (as :func:`render_view` draws it) before blending:
    ``A = Σ θ B V`` and ``C = Σ γ θ B V``, with ``values`` (N, 3) in place of the colours ``γ``
    when given (e.g. flow vectors; an additive particle's θ is still dimmed by the air in front
    of it, an alpha-blended one's values are not tinted). Shape: -> (A (1, H, W), C (3, H, W))."""
    device = torch.device("cpu") if device is None else torch.device(device)
    air = view_air(record, view, frame, device)
    sums = _view_sums(view, record, start, displacement, templates, dimming(air), beta=beta,
                      dtype=dtype, device=device, chunk_elements=chunk_elements, values=values)
    grid = planes(sums)[:, 0, 0]
    return grid[:1], grid[1:]


def render_first_frame(pair: FramePair, particles: Union[Particles, LayeredParticles],
                       templates: Optional[TemplateLibrary] = None, *,
                       beta: float = BETA_RENDER, device=None,
                       chunk_elements: Optional[int] = None):
    """Frame 1 of a pair alone (a sequence writes each frame once), the same bytes as
    ``render_pair(pair, particles).image1`` for a field record, or for combined weather whose
    layers are all field records (:func:`~weathergen.engine.rendering.combined.render_layers_view`).

    Shape: returns (image (1, 3, H, W), opacity (1, 1, H, W)).
    """
    check_pair_for_engine(pair)
    layered = isinstance(particles, LayeredParticles)
    if layered:
        if any(layer.optics is None for layer in particles.layers):
            raise ValueError("render_first_frame renders field records (every layer's optics "
                             "is set)")
        if len(particles.layers) == 1:
            particles, layered = particles.layers[0], False
        elif templates is not None:
            raise ConfigError("combined weather is drawn with each layer's own templates; "
                              "pass templates=None")
    elif particles.optics is None:
        raise ValueError("render_first_frame renders field records (particles.optics is set)")
    if device is not None:
        dev = resolve_device(device)
        pair, particles = pair.to(dev), particles.to(dev)
    _, c1, _ = reference_transforms(pair)
    image = pair.image1
    view = View(pair.intrinsics.to(image.device), c1.to(image.device), pair.depth1)
    if layered:
        out, alpha = render_layers_view(image, view, particles, beta=beta,
                                        chunk_elements=chunk_elements)
    else:
        lib = templates if templates is not None else load_templates(particles.settings.templates)
        start1, _, disp = pair_starts(particles, torch.float64, image.device)
        out, alpha = render_view(image, view, particles, start1, disp, lib, beta=beta,
                                 chunk_elements=chunk_elements)
    return out[None], alpha[None]
