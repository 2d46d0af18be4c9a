"""Per-frame appearance: rendering field-sampled particles one view at a time.

A record sampled from a weather field (:mod:`weathergen.engine.field`; ``record.optics`` set)
stores each particle's diameter in scene units instead of a footprint in pixels. Each view (a
frame of a pair, a frame of a sequence, a stereo camera) computes the particle's look from its own
camera depth ``z`` of the particle, so that a flake the camera approaches grows:

- footprint (pixels) ``f · diameter / z`` with ``f = sqrt(fx fy)``; below one pixel the stamp stays
  one pixel wide and θ is scaled by the footprint's area (``footprint^2``), so that far particles
  fade out smoothly instead of all drawing a full pixel;
- transparency ``θ · fade(z)``: a smoothstep from 0 at ``near`` to 1 at ``2 near`` and from 1 at
  ``far (1 - fade)`` to 0 at ``far``, so that particles never pop in or out at the ends of the
  drawn depth range;
- defocus: thin-lens circle of confusion of radius ``round(clip(f A |1/z - 1/focus| / 2, 0, 20))``
  pixels for aperture ``A`` focused at ``focus``, a normalised disc (light is spread, not added:
  no brightening).

The particles of a view are those :func:`view_mask` keeps: camera depth in ``[near, far]``, centre
or streak end inside the image widened by the stamp, and not behind the scene at its pixel (by
more than three ``depth_softness``; a particle just outside the image is tested against the
nearest border pixel, where its stamp reaches in). The mask depends on the view alone and the record keeps a
canonical order, so a frame is the same image in every pair (or sequence) that holds it.

Rendering reuses the renderer's stamp builder (:func:`~weathergen.engine.renderer.build_stamps`)
and splat core (:func:`~weathergen.engine.renderer._splat`), differentiable in the offsets, colour
and transparency as there. Occlusion uses ``β = min(beta, 1 / depth_softness)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from ..geometry import project, transform_points
from . import renderer
from .optics import FieldOptics
from .particles import Particles
from .renderer import RenderOutput, _blur_steps, _splat, build_stamps
from .sampling import NEAR, check_pair_for_engine, reference_transforms, resolve_device
from .templates import load_templates

MAX_DEFOCUS = 20


@dataclass
class View:
    """One camera looking at the particles.

    Shape: intrinsics (3, 3), cam_from_ref (4, 4), depth (1, H, W) camera-z of the scene.
    """

    intrinsics: torch.Tensor
    cam_from_ref: torch.Tensor
    depth: torch.Tensor

    @property
    def size(self) -> tuple[int, int]:
        return int(self.depth.shape[-2]), int(self.depth.shape[-1])


def focal(intrinsics: torch.Tensor) -> float:
    """``sqrt(fx fy)``: pixels per scene unit at unit depth."""
    k = intrinsics.double()
    return float(torch.sqrt(k[0, 0] * k[1, 1]))


def footprint(f: float, diameter: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Particle diameter on screen in pixels. Shape: (N,), (N,) -> (N,)."""
    return f * diameter / z


def defocus_radius(f: float, optics: FieldOptics, z: torch.Tensor) -> torch.Tensor:
    """Circle-of-confusion radius in whole pixels. Shape: (N,) -> (N,) int64."""
    if optics.aperture <= 0:
        return torch.zeros(z.shape, dtype=torch.long)
    r = 0.5 * f * optics.aperture * (1.0 / z - 1.0 / optics.focus).abs()
    return torch.floor(r.clamp(0, MAX_DEFOCUS) + 0.5).long()


def _smoothstep(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0, 1)
    return x * x * (3 - 2 * x)


def depth_fade(optics: FieldOptics, z: torch.Tensor) -> torch.Tensor:
    """Fade-in after ``near`` and fade-out before ``far``, in [0, 1]. Shape: any -> same."""
    fade_in = _smoothstep((z - optics.near) / optics.near)
    if optics.fade <= 0:
        return fade_in * (z <= optics.far).to(z.dtype)
    return fade_in * _smoothstep((optics.far - z) / (optics.fade * optics.far))


def view_mask(view: View, points: torch.Tensor, streak: torch.Tensor, diameter: torch.Tensor,
              optics: FieldOptics) -> torch.Tensor:
    """Which particles a view draws (see module doc).

    Shape: points (M, 3) reference coordinates, streak (M, 3) the streak's end minus its start,
    diameter (M,) -> (M,) bool. Computed in float64 on the CPU.
    """
    points, streak = points.double().cpu(), streak.double().cpu()
    diameter = diameter.double().cpu()
    cam = view.cam_from_ref.double().cpu()
    k = view.intrinsics.double().cpu()
    depth = view.depth.cpu()
    h, w = view.size
    f = focal(k)
    start = transform_points(cam, points)
    end = transform_points(cam, points + streak)
    z = start[:, 2]
    in_range = (z >= optics.near) & (z <= optics.far)
    safe_z = torch.where(in_range, z, torch.full_like(z, optics.far))
    reach = 0.5 * footprint(f, diameter, safe_z) + defocus_radius(f, optics, safe_z) + 2
    tolerance = 3 * optics.depth_softness

    def look(pts):
        pix, zz = project(pts, k)
        ahead = zz > 1e-6
        reaches = ahead & (pix[:, 0] >= -0.5 - reach) & (pix[:, 0] <= w - 0.5 + reach) \
            & (pix[:, 1] >= -0.5 - reach) & (pix[:, 1] <= h - 0.5 + reach)
        # the scene depth at the nearest pixel of the image (its border for a rim particle,
        # whose stamp reaches into the image there)
        col = torch.floor(pix[:, 0] + 0.5).clamp(0, w - 1).long()
        row = torch.floor(pix[:, 1] + 0.5).clamp(0, h - 1).long()
        return reaches & (zz <= depth[0, row, col].double() + tolerance)

    return in_range & (look(start) | look(end))


def view_appearance(record: Particles, z: torch.Tensor, f: float, resolution: int) -> Particles:
    """The record as one view sees it: footprint (as ``scale``, image pixels per pixel of a
    template of side ``resolution``), defocus radius and θ from the camera depth ``z``
    (detached, float64, shape (N,)). θ keeps its gradient."""
    optics = record.optics
    fp = footprint(f, record.scale.detach().double().cpu(), z)
    area = fp.clamp(max=1.0) ** 2
    factor = (depth_fade(optics, z) * area).to(device=record.transparency.device,
                                                dtype=record.transparency.dtype)
    return record.replace(scale=fp.clamp(min=1.0) / resolution, defocus=defocus_radius(f, optics, z),
                          transparency=record.transparency * factor)


@dataclass
class ViewSplat:
    """The accumulators of one view. Shape: alpha (1, H, W) = Σ θ B V; colour (3, H, W) = Σ γ θ B V;
    selected (n,) int64, the record's particles drawn in this view."""

    alpha: torch.Tensor
    colour: torch.Tensor
    selected: torch.Tensor


def splat_view(view: View, record: Particles, start: torch.Tensor, displacement: torch.Tensor,
               lib, *, beta: float, chunk_elements: int, dtype, device,
               values: Optional[torch.Tensor] = None, detach_occlusion: bool = False) -> ViewSplat:
    """Splat a field record into one view.

    Shape: start (N, 3) the particles' reference positions in this view's frame, displacement
    (N, 3) the motion their streaks follow; ``values`` (N, 3) replaces the colour (e.g. flow).
    """
    h, w = view.size
    optics = record.optics
    with torch.no_grad():
        if optics is None:     # the paper's fixed looks: every particle in front of the camera
            z_all = transform_points(view.cam_from_ref.double().cpu(),
                                     start.detach().double().cpu())[:, 2]
            keep = z_all > NEAR
        else:
            streak = float(record.settings.blur_length) * displacement.detach().double()
            keep = view_mask(view, start.detach(), streak, record.scale.detach(), optics)
        sel = torch.nonzero(keep).squeeze(1)
    zero_alpha = torch.zeros(1, h, w, dtype=dtype, device=device)
    if sel.numel() == 0:
        return ViewSplat(zero_alpha, torch.zeros(3, h, w, dtype=dtype, device=device), sel)
    sub = record.select(sel.to(record.device))
    s = start[sel.to(start.device)].to(device=device, dtype=dtype)
    d = displacement[sel.to(displacement.device)].to(device=device, dtype=dtype)
    cam = view.cam_from_ref.to(device)
    k = view.intrinsics.to(device)
    with torch.no_grad():
        z = transform_points(view.cam_from_ref.double().cpu(), s.detach().double().cpu())[:, 2]
    looks = sub if optics is None else view_appearance(sub, z, focal(view.intrinsics),
                                                       lib.resolution)
    if optics is not None:     # faded out entirely (at near or far): nothing to draw
        drawn = torch.nonzero(looks.transparency.detach() != 0).squeeze(1)
        if drawn.numel() < looks.count:
            looks, sub, s, d = looks.select(drawn), sub.select(drawn), s[drawn], d[drawn]
            sel = sel[drawn.cpu()]
        if looks.count == 0:
            return ViewSplat(zero_alpha, torch.zeros(3, h, w, dtype=dtype, device=device), sel)
    stamps = build_stamps([looks], lib, dtype=dtype, device=device, chunk_elements=chunk_elements)
    steps = _blur_steps(sub, dtype, device)
    n, kk = sub.count, steps.numel()
    pts = (s[:, None, :] + steps[None, :, None] * d[:, None, :]).reshape(-1, 3)
    pix, zz = project(transform_points(cam, pts), k)
    colour = values[sel.to(values.device)] if values is not None else sub.color
    inst = {
        "u": pix[:, 0], "v": pix[:, 1], "z": zz,
        "theta": (looks.transparency.to(device=device, dtype=dtype) / kk)[:, None]
        .expand(n, kk).reshape(-1),
        "color": colour.to(device=device, dtype=dtype)[:, None, :].expand(n, kk, 3).reshape(-1, 3),
        "target": torch.zeros(n * kk, dtype=torch.long, device=device),
        "particle": torch.arange(n, device=device)[:, None].expand(n, kk).reshape(-1),
    }
    beta_eff = float(beta) if optics is None else min(float(beta), 1.0 / optics.depth_softness)
    depth_flat = view.depth.to(device=device, dtype=dtype).reshape(-1)
    acc, _ = _splat(depth_flat, inst, stamps, h, w, beta_eff, chunk_elements, detach_occlusion)
    if acc is None:
        return ViewSplat(zero_alpha, torch.zeros(3, h, w, dtype=dtype, device=device), sel)
    return ViewSplat(acc[0].view(1, h, w), torch.stack([a.view(h, w) for a in acc[1:]]), sel)


def blend(image: torch.Tensor, splat: ViewSplat, mode: str) -> torch.Tensor:
    """Additive ``I + C`` or alpha ``I (1 - A) + C``, clamped. Shape: (3, H, W) -> (3, H, W)."""
    if mode == "alpha":
        return (image * (1 - splat.alpha) + splat.colour).clamp(0, 1)
    return (image + splat.colour).clamp(0, 1)


def render_view(image: torch.Tensor, view: View, record: Particles, start: torch.Tensor,
                displacement: torch.Tensor, lib, *, beta: float, chunk_elements: int,
                detach_occlusion: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """One weather frame. Shape: image (3, H, W) -> (image (3, H, W), opacity (1, H, W))."""
    sp = splat_view(view, record, start, displacement, lib, beta=beta,
                    chunk_elements=chunk_elements, dtype=image.dtype, device=image.device,
                    detach_occlusion=detach_occlusion)
    return blend(image, sp, record.settings.blend), sp.alpha.clamp(0, 1)


def pair_starts(record: Particles, dtype, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference positions in frames 1 and 2 and the displacement of a pair's record,
    ``P + δ1``, ``P + δ1 + M + δ2`` and ``M + δ2``, computed as the paper's renderer does."""
    pos = record.position.to(device=device, dtype=dtype)
    start1 = pos + record.offset1.to(device=device, dtype=dtype)
    displacement = record.motion.to(device=device, dtype=dtype) \
        + record.offset2.to(device=device, dtype=dtype)
    return start1, start1 + displacement, displacement


def render_per_frame(image1, image2, depth1, depth2, intrinsics, cam1_from_ref, cam2_from_ref,
                     records: Sequence[Particles], templates, *, beta: float,
                     chunk_elements: int, detach_occlusion: bool = False):
    """The per-frame-appearance path of :func:`weathergen.engine.renderer.render`: every pair and
    frame is rendered as its own view. Shapes as there; returns a ``RenderOutput``."""
    outs = {k: [] for k in ("image1", "image2", "opacity1", "opacity2")}
    for b, rec in enumerate(records):
        if rec.optics is None:   # a record of the paper's model in the same batch
            o = renderer.render(image1[b:b + 1], image2[b:b + 1], depth1[b:b + 1], depth2[b:b + 1],
                       intrinsics[b:b + 1], cam1_from_ref[b:b + 1], cam2_from_ref[b:b + 1],
                       [rec], templates, beta=beta, chunk_elements=chunk_elements,
                       detach_occlusion=detach_occlusion)
            for key in outs:
                outs[key].append(getattr(o, key)[0])
            continue
        dtype, device = image1.dtype, image1.device
        start1, start2, disp = pair_starts(rec, dtype, device)
        for t, (img, dep, cam, start) in enumerate(((image1, depth1, cam1_from_ref, start1),
                                                    (image2, depth2, cam2_from_ref, start2))):
            view = View(intrinsics[b], cam[b], dep[b])
            out, alpha = render_view(img[b], view, rec, start, disp, templates, beta=beta,
                                     chunk_elements=chunk_elements,
                                     detach_occlusion=detach_occlusion)
            outs[f"image{t + 1}"].append(out)
            outs[f"opacity{t + 1}"].append(alpha)
    return RenderOutput(**{k: torch.stack(v) for k, v in outs.items()})


def render_first_frame(pair, particles: Particles, templates=None, *, beta: float = 250.0,
                       device=None, chunk_elements: int = 1 << 21):
    """Frame 1 of a pair alone (a sequence writes each frame once), the same bytes as
    ``render_pair(pair, particles).image1`` for a field record.

    Shape: returns (image (1, 3, H, W), opacity (1, 1, H, W)).
    """
    check_pair_for_engine(pair)
    if particles.optics is None:
        raise ValueError("render_first_frame renders field records (particles.optics is set)")
    if device is not None:
        dev = resolve_device(device)
        pair, particles = pair.to(dev), particles.to(dev)
    lib = templates if templates is not None else load_templates(particles.settings.templates)
    _, c1, _ = reference_transforms(pair)
    image = pair.image1[None]
    start1, _, disp = pair_starts(particles, image.dtype, image.device)
    view = View(pair.intrinsics.to(image.device), c1.to(image.device), pair.depth1)
    out, alpha = render_view(image[0], view, particles, start1, disp, lib, beta=beta,
                             chunk_elements=chunk_elements)
    return out[None], alpha[None]


renderer.PER_FRAME_RENDERER = render_per_frame
