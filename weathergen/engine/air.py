"""The air of a render call: every view's atmospheres (:mod:`~weathergen.engine.atmosphere`),
composed once, applied to the scene and to the particles.

A pair's records may each carry an atmosphere (a fog layer, a rain layer's veil): their
extinctions add, ``τ = Σ_l τ_l``, and their airlights mix by optical depth,
``A = Σ_l τ_l A_l / τ`` (one atmosphere: its own ``A``). In each view:

- the scene ``J`` becomes ``J t + A (1 − t)``, ``t = exp(−τ)`` along each pixel's ray up to its
  surface (:meth:`Air.pixels`, :func:`fog_images`);
- a particle sees the air between it and the camera (:meth:`Air.dim`): an additive particle's
  light reaches the camera times ``t_p`` (its θ is multiplied by ``t_p``), an alpha-blended
  particle keeps its opacity and its colour becomes ``γ t_p + A_p (1 − t_p)``, with ``t_p`` and
  ``A_p`` along the ray to the middle of its streak. Behind it, the scene's own air is already in
  the composite, so ``I = (1 − a) I_scene + a (γ t_p + A_p (1 − t_p))`` for an alpha particle of
  opacity ``a``, and ``I_scene + t_p C`` for additive light ``C``: the single-scattering
  solution for a particle at distance ``d_p`` in front of a surface at ``d``;
- the opacity is ``1 − t (1 − α)``, ``α`` the particles' (:func:`combined_opacity`).

Views without an atmosphere are untouched (their bytes are those of a render without one).
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import torch

from .atmosphere import AirView, Atmosphere, ray_norms
from .tracks import Tracks


class Air:
    """The atmospheres of the V views of one render call. ``views[v]``: the :class:`AirView` of
    every atmosphere of view ``v``'s pair (empty where it has none)."""

    def __init__(self, views: Sequence[Sequence[AirView]]):
        self.views = [list(v) for v in views]

    @classmethod
    def of(cls, atmospheres: Sequence[Sequence[Atmosphere]], intrinsics: torch.Tensor,
           cam_from_ref: torch.Tensor, size: tuple[int, int], frames: Sequence[int],
           device=None) -> Optional["Air"]:
        """The air of V views, view ``v`` seeing ``atmospheres[v]`` in frame ``frames[v]`` of
        its pair (0 or 1); None where no view has any.
        Shape: intrinsics (V, 3, 3), cam_from_ref (V, 4, 4)."""
        if not any(atmospheres):
            return None
        return cls([[AirView(a, intrinsics[i], cam_from_ref[i], size, frames[i], device)
                     for a in atmospheres[i]] for i in range(len(atmospheres))])

    @property
    def count(self) -> int:
        return len(self.views)

    def reached(self) -> torch.Tensor:
        """Which views have air. Shape: (V,) bool (CPU)."""
        return torch.tensor([bool(v) for v in self.views])

    def pixels(self, depth: torch.Tensor, dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """Every pixel's transmission ``t`` along its ray up to its surface and the airlight
        ``A`` it gains, per view (``t = 1``, ``A = 0`` without air).
        Shape: depth (V, 1, H, W) -> (t (V, 1, H, W), A (V, 3, H, W)) in ``dtype``."""
        height, width = depth.shape[-2:]
        out_t, out_a = [], []
        for i, airs in enumerate(self.views):
            if not airs:
                out_t.append(torch.ones(1, height, width, dtype=dtype, device=depth.device))
                out_a.append(torch.zeros(3, height, width, dtype=dtype, device=depth.device))
                continue
            distance = airs[0].distances(depth[i])[0]
            v, u = _pixel_grid(height, width, distance.device)
            taus = [air.optical_depth(u, v, distance) for air in airs]
            t, airlight = _composed(taus, [air.atmosphere.airlight for air in airs])
            out_t.append(t.to(dtype)[None])
            airlight = airlight.to(dtype)
            out_a.append(airlight.view(3, 1, 1).expand(3, height, width) if airlight.dim() == 1
                         else airlight)
        return torch.stack(out_t), torch.stack(out_a)

    def dim(self, tracks: Tracks, alpha: torch.Tensor, tint: bool = True) -> Tracks:
        """Tracks seen through the air between each particle and its camera: additive tracks'
        θ times ``t_p``, alpha-blended tracks' colour ``γ t_p + A_p (1 − t_p)`` (unless not
        ``tint``: their colours are other values, e.g. flow vectors), both along the ray to the
        middle of the streak. ``alpha`` (V,) bool: which views draw the tracks alpha-blended.
        Tracks of views without air keep their bits."""
        if tracks.count == 0:
            return tracks
        reach = (tracks.samples - 1).clamp(min=0) * tracks.spacing
        middle = torch.addcmul(tracks.h0, (0.5 * reach)[:, None], tracks.hd)
        z = middle[:, 2]
        safe = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
        u, v = middle[:, 0] / safe, middle[:, 1] / safe
        count = tracks.count
        device = tracks.theta.device
        passed = torch.ones(count, dtype=torch.float64, device=device)
        light = torch.zeros(count, 3, dtype=torch.float64, device=device)
        for i, airs in enumerate(self.views):
            if not airs:
                continue
            rows = torch.nonzero(tracks.view == i).squeeze(1)
            if rows.numel() == 0:
                continue
            ui, vi, zi = u.index_select(0, rows), v.index_select(0, rows), z.index_select(0, rows)
            distance = zi.clamp(min=0) * ray_norms(airs[0].intrinsics, ui.detach(), vi.detach())
            taus = [air.optical_depth(ui, vi, distance) for air in airs]
            t, airlight = _composed(taus, [air.atmosphere.airlight for air in airs])
            passed = passed.index_put((rows,), t)
            light = light.index_put((rows,), (1 - t)[:, None] * airlight.expand(rows.numel(), 3)
                                    if airlight.dim() == 1 else
                                    (1 - t)[:, None] * airlight.T)
        dtype = tracks.theta.dtype
        alpha_track = alpha.to(device).index_select(0, tracks.view)
        theta = torch.where(alpha_track, tracks.theta, tracks.theta * passed.to(dtype))
        if not tint:
            return dataclasses.replace(tracks, theta=theta)
        colour = torch.where(alpha_track[:, None],
                             tracks.color * passed.to(dtype)[:, None] + light.to(dtype),
                             tracks.color)
        return dataclasses.replace(tracks, theta=theta, color=colour)


def _pixel_grid(height: int, width: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates ``(v, u)``. Shape: -> two (H, W) float64."""
    return torch.meshgrid(torch.arange(height, dtype=torch.float64, device=device),
                          torch.arange(width, dtype=torch.float64, device=device), indexing="ij")


def _composed(taus: Sequence[torch.Tensor], airlights: Sequence[torch.Tensor]
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The transmission of several atmospheres' optical depths and their airlight mixed by
    optical depth (one atmosphere: its own). Shape: taus each (...), airlights each (3,) ->
    (t (...), A (3,) or (3, ...)), float64."""
    if len(taus) == 1:
        return torch.exp(-taus[0]), airlights[0].double().to(taus[0].device)
    total = taus[0]
    for tau in taus[1:]:
        total = total + tau
    safe = torch.where(total > 0, total, torch.ones_like(total))
    mixed = sum(tau * a.double().to(tau.device).view(3, *[1] * tau.dim())
                for tau, a in zip(taus, airlights)) / safe
    first = airlights[0].double().to(total.device).view(3, *[1] * total.dim())
    return torch.exp(-total), torch.where(total > 0, mixed, first)


def fog_images(images: Sequence[torch.Tensor], transmission: torch.Tensor,
               airlight: torch.Tensor, air: Air) -> list[torch.Tensor]:
    """The scene through the air: ``J t + A (1 − t)`` where a view has air, ``J`` itself
    elsewhere. Shape: T images (B, 3, H, W) (view ``t B + b``); transmission (V, 1, H, W),
    airlight (V, 3, H, W) -> T images (B, 3, H, W)."""
    bsz = images[0].shape[0]
    has = air.reached()
    out = []
    for t, image in enumerate(images):
        rows = has[t * bsz:(t + 1) * bsz]
        if not bool(rows.any()):
            out.append(image)
            continue
        trans = transmission[t * bsz:(t + 1) * bsz]
        light = airlight[t * bsz:(t + 1) * bsz]
        fogged = torch.lerp(light, image, trans)
        keep = rows.to(image.device).view(-1, 1, 1, 1)
        out.append(torch.where(keep, fogged, image) if not bool(rows.all()) else fogged)
    return out


def combined_opacity(opacities: Sequence[torch.Tensor], transmission: torch.Tensor,
                     air: Air) -> list[torch.Tensor]:
    """The weather's opacity with the air's: ``1 − t (1 − α)`` where a view has air.
    Shape: T opacities (B, 1, H, W), transmission (V, 1, H, W) -> T opacities (B, 1, H, W)."""
    bsz = opacities[0].shape[0]
    has = air.reached()
    out = []
    for t, opacity in enumerate(opacities):
        rows = has[t * bsz:(t + 1) * bsz]
        if not bool(rows.any()):
            out.append(opacity)
            continue
        combined = 1 - transmission[t * bsz:(t + 1) * bsz] * (1 - opacity)
        keep = rows.to(opacity.device).view(-1, 1, 1, 1)
        out.append(torch.where(keep, combined, opacity) if not bool(rows.all()) else combined)
    return out


def pair_air(atmospheres: Sequence[Sequence[Atmosphere]], intrinsics: torch.Tensor,
             cam1_from_ref: torch.Tensor, cam2_from_ref: torch.Tensor, size: tuple[int, int],
             device=None) -> Optional[Air]:
    """The air of the 2B views of B pairs (view ``t B + b``: frame ``t`` of pair ``b``), pair
    ``b`` seeing ``atmospheres[b]`` (every layer's); None where no pair has any.
    Shape: intrinsics (B, 3, 3), cam*_from_ref (B, 4, 4)."""
    if not any(atmospheres):
        return None
    bsz = len(atmospheres)
    return Air.of(list(atmospheres) * 2, torch.cat((intrinsics, intrinsics)),
                  torch.cat((cam1_from_ref, cam2_from_ref)), size, [0] * bsz + [1] * bsz, device)


def record_atmospheres(record) -> list[Atmosphere]:
    """The atmospheres a pair's weather carries: a record's, or every layer's of combined
    weather (a :class:`~weathergen.engine.LayeredParticles`), in layer order."""
    layers = getattr(record, "layers", None)
    records = layers if layers is not None else (record,)
    return [r.atmosphere for r in records if r.atmosphere is not None]


def view_air(atmospheres: Sequence[Atmosphere], view, frame: int, device=None) -> Optional[Air]:
    """The air of one :class:`~weathergen.engine.View` (a frame of a sequence, a stereo camera)
    seeing ``atmospheres`` in frame ``frame`` (0 or 1) of their pair; None without any."""
    if not atmospheres:
        return None
    return Air.of([list(atmospheres)], view.intrinsics[None], view.cam_from_ref[None],
                  tuple(view.depth.shape[-2:]), [frame], device)
