"""The air of a render call: every view's atmospheres (:mod:`~weathergen.engine.weather.atmosphere`),
integrated along the rays of the views, composed once, applied to the scene and the particles.

A pair's records may each carry an atmosphere (a fog layer, a rain layer's veil): their
extinctions add, ``τ = Σ_l τ_l``, and their airlights mix by optical depth,
``A = Σ_l τ_l A_l / τ`` (one atmosphere: its own ``A``). In each view:

- the scene ``J`` becomes ``J t + A (1 − t)``, ``t = exp(−τ)`` along each pixel's ray up to its
  surface (:meth:`Air.pixels`, :func:`~weathergen.engine.rendering.composite.fog`);
- a particle sees the air between it and the camera (:meth:`Air.dim`): an additive particle's
  light reaches the camera times ``t_p`` (its θ is multiplied by ``t_p``), an alpha-blended
  particle keeps its opacity and its colour becomes ``γ t_p + A_p (1 − t_p)``, with ``t_p`` and
  ``A_p`` along the ray to the middle of its streak. Behind it, the scene's own air is already in
  the composite, so ``I = (1 − a) I_scene + a (γ t_p + A_p (1 − t_p))`` for an alpha particle of
  opacity ``a``, and ``I_scene + t_p C`` for additive light ``C``: the single-scattering
  solution for a particle at distance ``d_p`` in front of a surface at ``d``;
- the opacity is ``1 − t (1 − α)``, ``α`` the particles'
  (:func:`~weathergen.engine.rendering.composite.fogged_opacity`).

:func:`through_air` applies all three, in that order, for every entry point of the renderer; the
formulas live in the blend module, :mod:`~weathergen.engine.rendering.composite`.

Integration: a uniform atmosphere (``h = 0``, no explicit density) gives ``τ = β₀ L`` exactly. A
heterogeneous one is integrated by the midpoint rule along the rays of a coarse grid of pixels,
every ``step`` pixels (:data:`~weathergen.engine.weather.atmosphere.RAY_STEP`, fewer for short focal
lengths: at most :data:`~weathergen.engine.weather.atmosphere.RAY_ANGLE` apart), in
:data:`~weathergen.engine.weather.atmosphere.RAY_SAMPLES` intervals growing geometrically to
``sky_distance`` (:func:`~weathergen.engine.weather.atmosphere.ray_nodes`); a pixel, or a particle, reads
the cumulative integral at its own distance on the four coarse rays around it (linearly within an
interval) and interpolates them bilinearly.

Every view's atmospheres are laid out as *components* (one per atmosphere and view) and computed
together: the number of tensor operations does not grow with the views (the pairs) of the call,
each component's numbers depend on its own view alone (a frame is the same bytes alone or in a
batch), and views without an atmosphere are untouched.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Optional, Sequence

import torch
import torch.nn.functional as F

from ..weather.atmosphere import (RAY_ANGLE, RAY_SAMPLES, RAY_STEP, Atmosphere, ray_nodes,
                                  ray_norms, wrapped_lattice)
from .composite import fog, fogged_opacity, tinted
from .tracks import Tracks


class Air:
    """The atmospheres of the V views of one render call.

    ``atmospheres[v]``: the atmospheres view ``v`` sees (every layer's of its pair; none: the view
    is untouched), in frame ``frames[v]`` (0 or 1) of their pair. Shape: intrinsics (V, 3, 3),
    cam_from_ref (V, 4, 4) (each record's reference frame -> the view's camera), size (H, W).
    """

    def __init__(self, atmospheres: Sequence[Sequence[Atmosphere]], intrinsics: torch.Tensor,
                 cam_from_ref: torch.Tensor, size: tuple[int, int], frames: Sequence[int],
                 device=None):
        self.device = torch.device(device) if device is not None else cam_from_ref.device
        dev, f64 = self.device, torch.float64
        self.size = (int(size[0]), int(size[1]))
        self.atmospheres = [list(a) for a in atmospheres]
        comps = [(v, a) for v, atms in enumerate(self.atmospheres) for a in atms]
        self.components = [a for _, a in comps]
        self.frames = [int(frames[v]) for v, _ in comps]
        layers = max(len(a) for a in self.atmospheres)
        clear = len(comps)          # a component of clear air: no extinction, no airlight
        table = [[clear] * layers for _ in self.atmospheres]
        index = 0
        for v, atms in enumerate(self.atmospheres):
            for k in range(len(atms)):
                table[v][k] = index
                index += 1
        #: (V, L) component of each view's l-th atmosphere (the clear one where it has fewer)
        self.layer_of = torch.tensor(table, dtype=torch.long, device=dev).view(-1, layers)
        self.single = [sum(1 for c in row if c != clear) <= 1 for row in table]
        self.has_air = [bool(a) for a in self.atmospheres]
        self.has = torch.tensor(self.has_air)        #: which views have air (V,) bool, CPU
        self.view = torch.tensor([v for v, _ in comps], dtype=torch.long, device=dev)
        #: per view: fx, fy, cx, cy, skew
        self.camera = intrinsics.detach().to(device=dev, dtype=f64).reshape(-1, 9)[
            :, torch.tensor([0, 4, 2, 5, 1], device=dev)]
        self.cam_from_ref = cam_from_ref.detach().to(device=dev, dtype=f64)
        #: per component and the clear one: extinction, sky distance
        self.extinction = torch.tensor([a.extinction for a in self.components] + [0.0],
                                       dtype=f64, device=dev)
        self.sky = torch.tensor([a.sky_distance for a in self.components] + [1.0], dtype=f64,
                                device=dev)
        self.airlight = torch.stack([a.airlight.to(device=dev, dtype=f64)
                                     for a in self.components]
                                    + [torch.zeros(3, dtype=f64, device=dev)])
        self.hetero = [c for c, a in enumerate(self.components) if not a.uniform]
        #: per atmosphere slot l: whether any view's l-th atmosphere is heterogeneous (a slot of
        #: uniform or clear components alone needs no ray tables: τ = β₀ L)
        self.slot_hetero = [any(row[k] in self.hetero for row in table) for k in range(layers)]
        self._tables = None

    # -- optical depth -------------------------------------------------------------------------

    def optical_depth(self, comp: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                      distance: torch.Tensor, hetero: bool = True) -> torch.Tensor:
        """τ of component ``comp`` (the clear one, ``len(components)``: τ = 0) along the rays
        through image points ``(u, v)`` of its view up to ``distance`` (clamped to
        ``[0, sky_distance]``). Arguments broadcast to one shape; float64 (a heterogeneous
        component's table is read in its lattice's dtype). Differentiable in the points, the
        distance and the density lattices. ``hetero=False``: the caller knows that no element's
        component is heterogeneous (the tables are then not read)."""
        shape = torch.broadcast_shapes(comp.shape, u.shape, v.shape, distance.shape)
        flat = comp.reshape(-1)
        sky = self.sky.index_select(0, flat).view(comp.shape)
        length = torch.minimum(distance.double().clamp(min=0), sky)
        beta = self.extinction.index_select(0, flat).view(comp.shape)
        if not self.hetero or not hetero:
            return (beta * length).expand(shape)
        path = self._lookup(comp.expand(shape), u.expand(shape), v.expand(shape),
                            length.expand(shape))
        uniform = self._uniform.index_select(0, flat).view(comp.shape)
        return beta * torch.where(uniform, length, path)

    def _lookup(self, comp: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                length: torch.Tensor) -> torch.Tensor:
        """The midpoint integral of ρ up to ``length`` on the rays through ``(u, v)`` of each
        element's component, from the coarse rays' tables (:meth:`_build`; components without a
        table read table 0, for the caller to discard). float64."""
        t = self._build()
        m = RAY_SAMPLES
        slot = t["slot"].index_select(0, comp.reshape(-1)).view(comp.shape)
        step = t["step"].index_select(0, slot.reshape(-1)).view(slot.shape)
        rows = t["rows"].index_select(0, slot.reshape(-1)).view(slot.shape)
        cols = t["cols"].index_select(0, slot.reshape(-1)).view(slot.shape)
        k = self._interval(slot, length.detach())
        flat_ends = t["ends"].reshape(-1)
        part = length - flat_ends.index_select(0, (slot * (m + 1) + k).reshape(-1)).view(k.shape)
        dtype = t["density"].dtype
        part, step = part.to(dtype), step.to(dtype)
        fy = torch.minimum(((v.to(dtype) + 0.5) / step).clamp(min=0), (rows - 1).to(dtype))
        fx = torch.minimum(((u.to(dtype) + 0.5) / step).clamp(min=0), (cols - 1).to(dtype))
        y0 = torch.minimum(torch.floor(fy.detach()).long(), rows - 2)
        x0 = torch.minimum(torch.floor(fx.detach()).long(), cols - 2)
        wy, wx = fy - y0, fx - x0
        width = t["width"]
        first = ((slot * t["height"] + y0) * width + x0) * m + k
        flat_c, flat_d = t["cumulative"].reshape(-1), t["density"].reshape(-1)

        def along(offset):          # the integral up to ``length`` on a neighbour ray
            index = (first + offset * m).reshape(-1)
            c = flat_c.index_select(0, index + torch.div(index, m, rounding_mode="floor"))
            d = flat_d.index_select(0, index)
            return (c + part.reshape(-1) * d).view(first.shape)

        top = torch.lerp(along(0), along(1), wx)
        bottom = torch.lerp(along(width), along(width + 1), wx)
        return torch.lerp(top, bottom, wy).double()

    def _interval(self, slot: torch.Tensor, length: torch.Tensor) -> torch.Tensor:
        """The interval of each length along its component's rays (the last for the sky):
        ``floor(log(1 + L (q − 1) / first) / log q)`` for the geometric nodes, then moved by one
        where rounding put it beside the right one. Shape: (...) -> (...) int64."""
        t, m = self._tables, RAY_SAMPLES
        first = t["first"].index_select(0, slot.reshape(-1)).view(slot.shape)
        ratio = t["ratio"].index_select(0, slot.reshape(-1)).view(slot.shape)
        guess = torch.floor(torch.log1p(length * (ratio - 1) / first) / torch.log(ratio))
        k = guess.clamp(0, m - 1).long()
        flat = t["ends"].reshape(-1)
        base = slot * (m + 1)
        lower = flat.index_select(0, (base + k).reshape(-1)).view(k.shape)
        k = torch.where((lower > length) & (k > 0), k - 1, k)
        upper = flat.index_select(0, (base + k + 1).reshape(-1)).view(k.shape)
        return torch.where((upper <= length) & (k < m - 1), k + 1, k)

    def _build(self) -> dict:
        """The coarse rays of every heterogeneous component, in one pass: the densities at the
        intervals' midpoints (S, R, C, M) and their cumulative midpoint integrals
        (S, R, C, M + 1), padded to the largest grid of rays (each component's own rows and
        columns, from its view's focal length), with each component's grid and nodes."""
        if self._tables is not None:
            return self._tables
        dev, f64 = self.device, torch.float64
        height, width = self.size
        comps = self.hetero
        atms = [self.components[c] for c in comps]
        views = self.view.index_select(0, torch.tensor(comps, device=dev))
        cam = self.camera.index_select(0, views)
        focal = torch.sqrt(cam[:, 0] * cam[:, 1]).cpu().tolist()
        steps = [max(1, min(RAY_STEP, int(math.floor(f * RAY_ANGLE)))) for f in focal]
        rows = [-(-height // s) + 1 for s in steps]
        cols = [-(-width // s) + 1 for s in steps]
        big_r, big_c = max(rows), max(cols)
        step = torch.tensor(steps, dtype=f64, device=dev)
        grid = torch.arange(max(big_r, big_c), dtype=f64, device=dev)
        y = -0.5 + step[:, None] * grid[None, :big_r]                      # (S, R)
        x = -0.5 + step[:, None] * grid[None, :big_c]                      # (S, C)
        fx, fy, cx, cy, skew = (cam[:, i, None, None] for i in range(5))
        ry = (y[:, :, None] - cy) / fy
        rx = (x[:, None, :] - cx - skew * ry) / fx
        ray = torch.stack((rx, ry.expand_as(rx), torch.ones_like(rx)), -1)  # (S, R, C, 3)
        ray = ray / ray.norm(dim=-1, keepdim=True)
        pose = self.cam_from_ref.index_select(0, views)
        rot, trans = pose[:, None, None, :3, :3], pose[:, :3, 3]
        direction = (ray[..., :, None] * rot).sum(-2)                      # R^T d
        drift = torch.stack([a.drift[f].to(dev) for a, f in
                             zip(atms, [self.frames[c] for c in comps])])
        centre = -(trans[:, :, None] * pose[:, :3, :3]).sum(1) - drift      # −R^T t − drift
        voxel = torch.tensor([a.voxel for a in atms], dtype=f64, device=dev)
        nodes = [ray_nodes(float(a.sky_distance)) for a in atms]
        ends = torch.stack([n[0] for n in nodes]).to(dev)                  # (S, M + 1)
        mids = torch.stack([n[1] for n in nodes]).to(dev)
        lengths = torch.stack([n[2] for n in nodes]).to(dev)
        dtype = f64 if any(a.density is not None and a.density.dtype == f64 for a in atms) \
            else torch.float32
        lattices = torch.stack([a.lattice(dtype, dev) for a in atms])       # (S, P, P, P)
        density = _sample_rays(lattices, centre / voxel[:, None], direction,
                               mids / voxel[:, None])                     # (S, R, C, M)
        cumulative = torch.cat((torch.zeros(*density.shape[:-1], 1, dtype=dtype, device=dev),
                                torch.cumsum(density * lengths[:, None, None].to(dtype), -1)),
                               -1)
        slot = torch.zeros(len(self.components) + 1, dtype=torch.long, device=dev)
        slot[torch.tensor(comps, device=dev)] = torch.arange(len(comps), device=dev)
        uniform = torch.ones(len(self.components) + 1, dtype=torch.bool, device=dev)
        uniform[torch.tensor(comps, device=dev)] = False
        self._uniform = uniform
        self._tables = {"slot": slot, "step": step, "ends": ends, "density": density,
                        "first": lengths[:, 0].clone(), "ratio": lengths[:, 1] / lengths[:, 0],
                        "cumulative": cumulative, "height": big_r, "width": big_c,
                        "rows": torch.tensor(rows, device=dev),
                        "cols": torch.tensor(cols, device=dev)}
        return self._tables

    def _through(self, view: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                 distance: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The transmission ``t`` and mixed airlight ``A`` along the rays of views ``view``
        through ``(u, v)`` up to ``distance``, every atmosphere of each view composed.
        Shape: broadcast (...) -> (t (...), A (..., 3)), float64."""
        comps = self.layer_of.index_select(0, view.reshape(-1)).view(*view.shape, -1)
        comp0 = comps[..., 0]
        total = self.optical_depth(comp0, u, v, distance, self.slot_hetero[0])
        airlight = self.airlight.index_select(0, comp0.reshape(-1)).view(*comp0.shape, 3)
        if all(self.single):
            return torch.exp(-total), airlight.expand(*total.shape, 3)
        airlight = airlight.expand(*total.shape, 3)
        mixed = total[..., None] * airlight
        for layer in range(1, comps.shape[-1]):
            comp = comps[..., layer]
            tau = self.optical_depth(comp, u, v, distance, self.slot_hetero[layer])
            total = total + tau
            light = self.airlight.index_select(0, comp.reshape(-1)).view(*comp.shape, 3)
            mixed = mixed + tau[..., None] * light
        single = torch.tensor(self.single, device=self.device).index_select(
            0, view.reshape(-1)).view(view.shape)
        safe = torch.where(total > 0, total, torch.ones_like(total))
        mixed = torch.where((single | (total <= 0))[..., None], airlight.expand_as(mixed),
                            mixed / safe[..., None])
        return torch.exp(-total), mixed

    # -- the scene and the particles -----------------------------------------------------------

    def pixels(self, depth: torch.Tensor, dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """Every pixel's transmission ``t`` along its ray up to its surface and the airlight
        ``A`` it gains, per view (``t = 1``, ``A = 0`` without air).
        Shape: depth (V, 1, H, W) -> (t (V, 1, H, W), A (V, 3, H, W)) in ``dtype``."""
        count = depth.shape[0]
        height, width = depth.shape[-2:]
        dev = self.device
        view = torch.arange(count, device=dev)[:, None, None]
        v = torch.arange(height, dtype=torch.float64, device=dev)[None, :, None]
        u = torch.arange(width, dtype=torch.float64, device=dev)[None, None, :]
        distance = depth[:, 0].to(dev).double() * ray_norms(self.camera.view(-1, 1, 1, 5), u, v)
        # (a view without air reads the clear component: t = exp(0) = 1 and A = 0 exactly)
        t, airlight = self._through(view, u, v, distance)
        return t[:, None].to(dtype), airlight.permute(0, 3, 1, 2).to(dtype)

    def dim(self, tracks: Tracks, alpha: torch.Tensor, tint: bool = True) -> Tracks:
        """Tracks seen through the air between each particle and its camera: additive tracks'
        θ times ``t_p``, alpha-blended tracks' colour ``γ t_p + A_p (1 − t_p)`` (unless not
        ``tint``: their colours are other values, e.g. flow vectors), both along the ray to the
        middle of the streak, at its detached position (no gradient to the offsets through
        ``t_p``). ``alpha`` (V,) bool: which views draw the tracks alpha-blended. Tracks of
        views without air keep their bits."""
        if tracks.count == 0:
            return tracks
        reach = (tracks.samples - 1).clamp(min=0) * tracks.spacing
        # (a look: it follows the detached position, as a field particle's footprint and fade
        # do; gradients reach the density lattice and the airlight)
        middle = torch.addcmul(tracks.h0.detach(), (0.5 * reach)[:, None], tracks.hd.detach())
        z = middle[:, 2]
        safe = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
        u, v = middle[:, 0] / safe, middle[:, 1] / safe
        view = tracks.view.to(self.device)
        distance = z.clamp(min=0) * ray_norms(self.camera.index_select(0, view), u, v)
        # (a view without air reads the clear component: t = 1 and A = 0, which keep the bits)
        t, airlight = self._through(view, u, v, distance)
        dtype = tracks.theta.dtype
        passed = t.to(dtype)
        alpha_track = alpha.to(self.device).index_select(0, view)
        theta = torch.where(alpha_track, tracks.theta, tracks.theta * passed)
        if not tint:
            return dataclasses.replace(tracks, theta=theta)
        colour = torch.where(alpha_track[:, None], tinted(tracks.color, passed, t, airlight),
                             tracks.color)
        return dataclasses.replace(tracks, theta=theta, color=colour)


def _sample_rays(lattices: torch.Tensor, origin: torch.Tensor, direction: torch.Tensor,
                 distances: torch.Tensor) -> torch.Tensor:
    """Each lattice at ``origin + s · direction`` for its rays and distances ``s``, in voxel
    units. The origin is wrapped into the lattice in float64 and the ray's course added in the
    lattices' dtype (a few hundred voxels at most), so a float32 lattice is read in float32.
    Shape: lattices (S, P, P, P), origin (S, 3), direction (S, R, C, 3), distances (S, M) ->
    (S, R, C, M)."""
    size = lattices.shape[-1]
    dtype = lattices.dtype
    start = torch.remainder(origin, size).flip(-1).to(dtype)           # grid_sample: x, y, z
    course = direction.flip(-1).to(dtype)[..., None, :] \
        * distances.to(dtype)[:, None, None, :, None]
    coords = torch.remainder(start[:, None, None, None] + course, size) * (2.0 / size) - 1
    count = lattices.shape[0]
    volumes = torch.cat([wrapped_lattice(lattice) for lattice in lattices]) \
        if count > 1 else wrapped_lattice(lattices[0])
    out = F.grid_sample(volumes, coords.reshape(count, -1, 1, 1, 3), mode="bilinear",
                        padding_mode="border", align_corners=True)
    return out.reshape(coords.shape[:-1])


# -- a render call's air ---------------------------------------------------------------------

def dimming(air: Optional[Air]) -> Callable[..., Tracks]:
    """How particles are seen through ``air`` (None: no view has any): :meth:`Air.dim`, or the
    tracks as they are. The entry points that stop at the splat's sums use this step alone."""
    return air.dim if air is not None else lambda tracks, *_, **__: tracks


def through_air(air: Optional[Air], depth: torch.Tensor, images: Sequence[torch.Tensor], draw
                ) -> tuple[list, list, Optional[torch.Tensor]]:
    """Weather drawn into ``images`` seen through the air, as every entry point of the renderer
    applies it: ``draw(dim)`` draws the particles seen through ``dim`` (:func:`dimming`) and
    returns ``blend(images) -> (frames, opacities, reached (V,) or None)``; the scene is fogged,
    blended, its opacities take the air's and views with air count as reached (the formulas:
    :mod:`~weathergen.engine.rendering.composite`). Shape: T images (B, 3, H, W) (view
    ``t B + b``), depth (V, 1, H, W) the views' scene depth."""
    blend = draw(dimming(air))
    if air is None:
        return blend(images)
    transmission, airlight = air.pixels(depth, images[0].dtype)
    frames, opacities, reached = blend(_where_air(
        images, air, lambda image, views: fog(airlight[views], image, transmission[views])))
    opacities = _where_air(opacities, air,
                           lambda opacity, views: fogged_opacity(opacity, transmission[views]))
    return frames, opacities, None if reached is None else reached | air.has.to(reached.device)


def _where_air(frames: Sequence[torch.Tensor], air: Air, through) -> list[torch.Tensor]:
    """Each frame's batch (B, C, H, W) (views ``t B .. t B + B − 1``) as ``through(frame,
    views)`` gives it where a view has air, the frame itself elsewhere (a frame none of whose
    views has air is returned as it is)."""
    bsz = frames[0].shape[0]
    out = []
    for t, frame in enumerate(frames):
        views = slice(t * bsz, (t + 1) * bsz)
        rows = air.has_air[views]
        if not any(rows):
            out.append(frame)
            continue
        changed = through(frame, views)
        if not all(rows):
            keep = air.has[views].to(frame.device).view(-1, 1, 1, 1)
            changed = torch.where(keep, changed, frame)
        out.append(changed)
    return out


def pair_air(records: Sequence, intrinsics: torch.Tensor, cam1_from_ref: torch.Tensor,
             cam2_from_ref: torch.Tensor, size, device=None) -> Optional[Air]:
    """The air of the 2B views of B pairs (view ``t B + b``: frame ``t`` of pair ``b``), pair
    ``b`` seeing the atmospheres of ``records[b]`` (every layer's); None where no pair has any.
    Shape: intrinsics (B, 3, 3), cam*_from_ref (B, 4, 4), size (H, W)."""
    atmospheres = [record_atmospheres(r) for r in records]
    if not any(atmospheres):
        return None
    bsz = len(atmospheres)
    return Air(atmospheres * 2, torch.cat((intrinsics, intrinsics)),
               torch.cat((cam1_from_ref, cam2_from_ref)), tuple(size), [0] * bsz + [1] * bsz,
               device)


def view_air(record, view, frame: int, device=None) -> Optional[Air]:
    """The air of one :class:`~weathergen.engine.View` (a frame of a sequence, a stereo camera)
    seeing the atmospheres of ``record`` in frame ``frame`` (0 or 1) of its pair; None without
    any."""
    atmospheres = record_atmospheres(record)
    if not atmospheres:
        return None
    return Air([list(atmospheres)], view.intrinsics[None], view.cam_from_ref[None],
               tuple(view.depth.shape[-2:]), [frame], device)


def record_atmospheres(record) -> list[Atmosphere]:
    """The atmospheres a pair's weather carries: a record's, or every layer's of combined
    weather (a :class:`~weathergen.engine.LayeredParticles`), in layer order."""
    layers = getattr(record, "layers", None)
    records = layers if layers is not None else (record,)
    return [r.atmosphere for r in records if r.atmosphere is not None]
