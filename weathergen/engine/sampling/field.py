"""Weather fields: particles at world positions with a density, shared by every camera that sees them.

The paper's model (:mod:`weathergen.engine.sampling.pair`) places a fixed number of *visible*
particles in front of camera 1 of one pair. A field instead fills the space around the cameras
with a *density* (particles per cubic scene unit), so that the weather seen stays the same as the
cameras move, whatever the scene hides, and one field serves a pair, a whole sequence and a second
(stereo) camera alike.

Design: a periodic tile
-----------------------
A seeded cube of side ``L`` (the preset's ``tile``) holds ``round(density L^3)`` particles, each
with a start position, a constant velocity (fall along the world's down axis, jitter, wind) and its
looks (diameter, template, rotation, colour). Space is tiled with copies of this cube, so particle
``j`` of copy ``k`` (an integer 3-vector) is at ``start_j + n step_j + k L`` in frame ``n``
(``step_j = velocity_j / frame_rate``): every trajectory is a straight line, and at every instant
the particles form the same periodic set, moved. Any region of volume ``V`` holds about
``density V`` particles in every frame (exactly that for whole tiles): cameras that move through the
field see new particles enter and none pile up, and the field is never re-sampled.

A frame's particles are enumerated from the copies that meet its view volume (the frustum from the
preset's ``near`` to ``far``, widened by the largest footprint and streak) and kept when
:func:`~weathergen.engine.rendering.tracks.view_mask` says so: in that depth range, inside the image (or
close enough that the stamp reaches it), and not behind the scene surface at its pixel. Particles
inside solid objects are therefore never drawn (no camera sees them in front of the surface), and a
near wall hides the weather behind it instead of concentrating it in the visible strip.

Exact arithmetic
----------------
Positions and per-frame steps are integers on a grid of ``quantum = 2^floor(log2(L) - 16)`` scene
units (``L`` itself is rounded to the grid): frame ``n`` of trajectory ``(j, k)`` is computed in
integers, then scaled by a power of two, so it is the same float whether it is reached as the
first frame of pair ``(n, n + 1)`` or as position + motion of pair ``(n - 1, n)``. In float32 (the
particle record's storage) this holds within ``2^24`` quanta of the origin (``256 L``, e.g. 1 km
for a 4 m tile). A frame is thus the same image in every pair that holds it.

Every random number is drawn on the CPU in float64 from one seeded ``torch.Generator`` (the field's
seed, derived per scene), so the same seed gives the same field on any machine.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import torch

from ...errors import ConfigError
from ...framepair import FramePair
from ...geometry import invert_rigid, transform_points
from ..weather.atmosphere import DEFAULT_AIRLIGHT, Atmosphere, estimate_airlight
from ..records.layered import LayeredParticles, layer_seed
from ..weather.presets import CombinedPreset, FieldPreset
from ..records.particles import Particles, empty_particles
from ..common import check_pair_for_engine, reference_transforms, resolve_device
from .pair import (cpu_generator, euler_rotations, expect_kind, hls_to_rgb, rgb_to_hls,
                   sample_particles, world_down)
from ..records.settings import RenderSettings
from ..weather.templates import TemplateLibrary, load_templates
from ..views import MAX_DEFOCUS, View, focal, view_mask, view_windows

#: Bits of the grid below the tile side: quantum = 2^floor(log2(L) - GRID_BITS).
GRID_BITS = 16
#: Sub-cells per tile axis for culling a copy of the tile against a view volume.
SUBDIV = 4


def scene_seed(run_seed: int, dataset: str, split: str, scene: str) -> int:
    """The 63-bit seed of one scene's field, from the run seed and the scene's identity alone."""
    digest = hashlib.sha256(f"weathergen-field:{run_seed}:{dataset}:{split}:{scene}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def horizontal_axes(down: torch.Tensor) -> tuple[int, int]:
    """The two reference axes the preset's ``wind`` runs along, for an axis-aligned ``down``:
    up/down along z -> (x, y); along y -> (z, x); along x -> (y, z)."""
    axis = int(down.abs().argmax())
    return (axis + 1) % 3, (axis + 2) % 3


@dataclass
class Field:
    """One seeded tile of particles, repeated through the reference frame (see module doc).

    Shape (N particles per tile):
        start: (N, 3) int64, position in frame 0, in quanta, in [0, tile_units).
        step: (N, 3) int64, displacement per frame, in quanta.
        diameter: (N,) float64 scene units; transparency (N,) base θ; color (N, 3) RGB [0, 1];
        template: (N,) int64; rotation: (N,) radians.
    """

    start: torch.Tensor
    step: torch.Tensor
    diameter: torch.Tensor
    transparency: torch.Tensor
    color: torch.Tensor
    template: torch.Tensor
    rotation: torch.Tensor
    quantum: float
    tile_units: int
    frame: str
    frame_rate: float
    streak: float                 # streak length as a fraction of one frame's displacement
    preset: FieldPreset
    templates: str
    templates_digest: str
    atmosphere: Optional[Atmosphere] = None   # its drift: the wind's per frame (1, 3)

    @property
    def count(self) -> int:
        return int(self.start.shape[0])

    @property
    def tile(self) -> float:
        return self.tile_units * self.quantum

    def max_streak(self) -> float:
        """Longest streak vector of any particle, scene units."""
        if self.count == 0:
            return 0.0
        return float(self.step.double().norm(dim=1).max()) * self.quantum * self.streak

    def positions(self, j: torch.Tensor, k: torch.Tensor, frame: int) -> torch.Tensor:
        """World positions of trajectories ``(j, k)`` in frame ``frame``, exact (see module doc).
        Shape: j (M,), k (M, 3) -> (M, 3) float64."""
        m = self.start[j] + frame * self.step[j] + k * self.tile_units
        return m.double() * self.quantum

    def candidates(self, view: View, frame: int, chunk: int = 1 << 20
                   ) -> tuple[torch.Tensor, torch.Tensor]:
        """Trajectories ``(j (M,), k (M, 3))`` drawn in ``view`` at ``frame``, in canonical order
        (by ``j``, then ``k``), chosen by :func:`view_mask`. The tests run on the device of the
        view's depth (integer arithmetic, and the mask in float64); the answer is on the CPU."""
        if self.count == 0:
            return torch.zeros(0, dtype=torch.long), torch.zeros(0, 3, dtype=torch.long)
        dev = view.depth.device
        lo, hi = self._view_box(view)
        q, lu = self.quantum, self.tile_units
        start, step = self.start.to(dev), self.step.to(dev)
        unwrapped = start + frame * step                                  # (N, 3) quanta
        base = torch.remainder(unwrapped, lu)
        shift = torch.div(unwrapped - base, lu, rounding_mode="floor")   # copy of the start
        cell_lo = torch.floor(lo / (q * lu)).long()
        cell_hi = torch.floor(hi / (q * lu)).long()
        ranges = [torch.arange(int(cell_lo[a]), int(cell_hi[a]) + 1) for a in range(3)]
        cells = torch.cartesian_prod(*ranges).reshape(-1, 3)
        cells = cells[self._boxes_in_view(view, cells.double(), 1.0)].to(dev)
        # Within the tile, particles are binned into SUBDIV^3 sub-cells; only the sub-cells of
        # each copy that meet the view volume are tested particle by particle.
        sd = SUBDIV
        sub = torch.div(base * sd, lu, rounding_mode="floor").clamp(0, sd - 1)
        sub_id = (sub[:, 0] * sd + sub[:, 1]) * sd + sub[:, 2]
        order = torch.argsort(sub_id, stable=True)
        counts = torch.bincount(sub_id, minlength=sd ** 3)
        offsets = torch.cumsum(counts, 0) - counts
        sub_xyz = torch.stack(torch.meshgrid(*(torch.arange(sd, device=dev),) * 3,
                                             indexing="ij"), -1)
        sub_xyz = sub_xyz.reshape(-1, 3).double()
        streak = step.double() * q * self.streak
        diameter = self.diameter.to(dev)
        found_j, found_k = [], []
        windows = view_windows(view)
        per = max(1, chunk // (sd ** 3))
        for c0 in range(0, cells.shape[0], per):
            cell = cells[c0:c0 + per]
            corner = cell[:, None, :].double() + sub_xyz[None] / sd          # (C, S, 3) tiles
            keep = self._boxes_in_view(view, corner.reshape(-1, 3), 1.0 / sd)
            keep = keep.reshape(cell.shape[0], -1) & (counts > 0)[None]
            ci, si = torch.nonzero(keep, as_tuple=True)
            if ci.numel() == 0:
                continue
            size = counts[si]
            rep = torch.repeat_interleave(torch.arange(si.numel(), device=dev), size)
            within = torch.arange(int(size.sum()), device=dev) - torch.repeat_interleave(
                torch.cumsum(size, 0) - size, size)
            j = order[offsets[si][rep] + within]
            copy = cell[ci][rep]
            pts = (base[j] + copy * lu).double() * q
            ok = view_mask(view, pts, streak[j], diameter[j], self.preset.optics(), windows)
            found_j.append(j[ok].cpu())
            found_k.append((copy[ok] - shift[j[ok]]).cpu())
        if not found_j:
            return torch.zeros(0, dtype=torch.long), torch.zeros(0, 3, dtype=torch.long)
        return _canonical(torch.cat(found_j), torch.cat(found_k))

    def _view_planes(self, view: View) -> torch.Tensor:
        """The widened view volume as inward planes ``n . x + c >= 0`` in camera coordinates:
        near, far and the four sides through the widened image border. Shape: (6, 4)."""
        h, w = view.size
        k = view.intrinsics.double().cpu()
        f = focal(k)
        optics = self.preset.optics()
        margin = 0.5 * f * float(self.diameter.max()) / optics.near + MAX_DEFOCUS + 2
        x0, x1 = -0.5 - margin, w - 0.5 + margin
        y0, y1 = -0.5 - margin, h - 0.5 + margin

        def ray(x, y):
            v = (y - float(k[1, 2])) / float(k[1, 1])
            u = (x - float(k[0, 2]) - float(k[0, 1]) * v) / float(k[0, 0])
            return torch.tensor([u, v, 1.0], dtype=torch.float64)

        tl, tr, bl, br = ray(x0, y0), ray(x1, y0), ray(x0, y1), ray(x1, y1)
        planes = []
        for a, b in ((tl, bl), (br, tr), (tr, tl), (bl, br)):   # left, right, top, bottom
            n = torch.linalg.cross(b, a)
            planes.append(torch.cat((n / n.norm(), torch.zeros(1, dtype=torch.float64))))
        planes.append(torch.tensor([0, 0, 1.0, -optics.near], dtype=torch.float64))
        planes.append(torch.tensor([0, 0, -1.0, optics.far], dtype=torch.float64))
        return torch.stack(planes)

    def _boxes_in_view(self, view: View, corners: torch.Tensor, fraction: float) -> torch.Tensor:
        """Which axis-aligned boxes (lowest corner ``corners`` in tile units, side ``fraction``
        tiles) may hold a particle of the view: the box's bounding sphere, widened by the
        longest streak, meets the inner side of every plane. Shape: (C, 3) -> (C,)."""
        side = self.tile * fraction
        centres = (corners + 0.5 * fraction) * self.tile
        cam = transform_points(view.cam_from_ref.double().to(centres.device), centres)
        planes = self._view_planes(view).to(centres.device)
        dist = cam @ planes[:, :3].T + planes[:, 3]
        radius = 0.5 * math.sqrt(3) * side + self.max_streak()
        return (dist >= -radius).all(1)

    def _view_box(self, view: View) -> tuple[torch.Tensor, torch.Tensor]:
        """Axis-aligned reference-frame box around the view volume, widened by the largest
        stamp (as a fraction of depth) and the longest streak. Shape: -> (3,), (3,) float64."""
        h, w = view.size
        k = view.intrinsics.double().cpu()
        f = float(torch.sqrt(k[0, 0] * k[1, 1]))
        optics = self.preset.optics()
        # the widest stamp: largest diameter at the near plane, plus the widest defocus disc
        margin = 0.5 * f * float(self.diameter.max()) / optics.near + MAX_DEFOCUS + 2
        xs = torch.tensor([-0.5 - margin, w - 0.5 + margin], dtype=torch.float64)
        ys = torch.tensor([-0.5 - margin, h - 0.5 + margin], dtype=torch.float64)
        corners = []
        for z in (optics.near, optics.far):
            for x in xs:
                for y in ys:
                    v = (y - k[1, 2]) / k[1, 1]
                    u = (x - k[0, 2] - k[0, 1] * v) / k[0, 0]
                    corners.append(torch.stack((u * z, v * z, torch.tensor(z, dtype=torch.float64))))
        ref = transform_points(invert_rigid(view.cam_from_ref.double().cpu()), torch.stack(corners))
        pad = self.max_streak()
        return ref.min(0).values - pad, ref.max(0).values + pad


def _canonical(j: torch.Tensor, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Unique trajectories sorted by (j, kx, ky, kz)."""
    if j.numel() == 0:
        return j, k
    lo = k.min(0).values
    span = k.max(0).values - lo + 1
    kk = k - lo
    key = ((j * span[0] + kk[:, 0]) * span[1] + kk[:, 1]) * span[2] + kk[:, 2]
    key = torch.unique(key)                 # sorted
    kz = torch.remainder(key, span[2])
    rest = torch.div(key, span[2], rounding_mode="floor")
    ky = torch.remainder(rest, span[1])
    rest = torch.div(rest, span[1], rounding_mode="floor")
    kx = torch.remainder(rest, span[0])
    j = torch.div(rest, span[0], rounding_mode="floor")
    return j, torch.stack((kx, ky, kz), 1) + lo


def make_field(preset: FieldPreset, seed, *, down: torch.Tensor, frame_rate: float,
               frame: str = "world", templates: Optional[TemplateLibrary] = None,
               airlight: Optional[Sequence[float]] = None) -> Field:
    """Draw one field tile from ``seed`` (an int or a CPU generator).

    ``down`` (3,) is the reference frame's down axis (see :func:`world_down`); ``frame_rate``
    turns the preset's speeds (per second) into steps per frame. A preset with an atmosphere
    gets one (:func:`field_atmosphere`); ``airlight`` (RGB in [0, 1]) is its airlight where the
    preset says ``auto`` (default: :data:`~weathergen.engine.weather.atmosphere.DEFAULT_AIRLIGHT`).
    """
    if not frame_rate > 0:
        raise ConfigError(f"frame rate {frame_rate!r}: must be > 0")
    atmosphere = field_atmosphere(preset, seed, down=down, frame_rate=frame_rate,
                                  airlight=airlight)
    gen = cpu_generator(seed)
    lib = templates if templates is not None else load_templates(preset.templates)
    quantum = 2.0 ** math.floor(math.log2(preset.tile) - GRID_BITS)
    tile_units = max(1, int(round(preset.tile / quantum)))
    n = preset.tile_count()
    down = down.double().cpu()
    u = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    start = torch.floor(u * tile_units).long().clamp(max=tile_units - 1)
    angle = math.radians(preset.angle_jitter)
    u = torch.rand(n, 5, generator=gen, dtype=torch.float64)
    rot = euler_rotations((2 * u[:, :3] - 1) * angle)
    speed = preset.fall_speed * (1 + (2 * u[:, 3] - 1) * preset.speed_jitter)
    velocity = (rot @ down) * speed[:, None]
    a, b = horizontal_axes(down)
    velocity[:, a] += preset.wind[0]
    velocity[:, b] += preset.wind[1]
    step = torch.round(velocity / frame_rate / quantum).long()
    diameter = preset.diameter * (1 + (2 * u[:, 4] - 1) * preset.diameter_jitter)
    diameter = diameter.float().double()     # the record's storage precision: one mask for both

    u = torch.rand(n, 4, generator=gen, dtype=torch.float64)
    template = torch.randint(0, lib.count, (n,), generator=gen)
    rotation = u[:, 0] * 2 * math.pi
    hls = rgb_to_hls(torch.tensor(preset.color, dtype=torch.float64) / 255.0).expand(n, 3)
    hls = hls + (2 * u[:, 1:4] - 1) * torch.tensor(
        [preset.hue_jitter / 360.0, preset.lightness_jitter, preset.saturation_jitter],
        dtype=torch.float64)
    hls = torch.stack((torch.remainder(hls[:, 0], 1.0), hls[:, 1].clamp(0, 1),
                       hls[:, 2].clamp(0, 1)), -1)
    color = hls_to_rgb(hls).clamp(0, 1)
    return Field(start=start, step=step, diameter=diameter,
                 transparency=torch.full((n,), preset.transparency, dtype=torch.float64),
                 color=color, template=template, rotation=rotation, quantum=quantum,
                 tile_units=tile_units, frame=frame, frame_rate=frame_rate,
                 streak=preset.streak_fraction(frame_rate), preset=preset,
                 templates=lib.name, templates_digest=lib.digest, atmosphere=atmosphere)


def field_atmosphere(preset: FieldPreset, seed, *, down: torch.Tensor, frame_rate: float,
                     airlight: Optional[Sequence[float]] = None) -> Optional[Atmosphere]:
    """The atmosphere of a field preset (None for clear air), its ``drift`` one frame's wind
    (1, 3) (:func:`field_record` turns it into the pair's frames), its density lattice seeded
    from ``seed`` (a generator's initial seed), its airlight the preset's colour or, for
    ``auto``, ``airlight``."""
    if not preset.has_atmosphere:
        return None
    if isinstance(preset.airlight, tuple):
        light = torch.tensor(preset.airlight, dtype=torch.float64) / 255.0
    else:
        light = torch.tensor(DEFAULT_AIRLIGHT if airlight is None else list(airlight),
                             dtype=torch.float64).clamp(0, 1)
    step = torch.zeros(3, dtype=torch.float64)
    a, b = horizontal_axes(down.double().cpu())
    step[a] = preset.wind[0] / frame_rate
    step[b] = preset.wind[1] / frame_rate
    base = seed.initial_seed() if isinstance(seed, torch.Generator) else int(seed)
    return Atmosphere(extinction=preset.extinction, airlight=light, drift=step[None],
                      heterogeneity=preset.heterogeneity, scale=preset.heterogeneity_scale,
                      seed=base, sky_distance=preset.sky_distance)


def field_record(fld: Field, j: torch.Tensor, k: torch.Tensor, frame: int, frames: int = 1
                 ) -> Particles:
    """The particle record of trajectories ``(j, k)``: positions in frame ``frame``, motion over
    ``frames`` frames, the field's looks and optics. Quantized (storage precision)."""
    preset = fld.preset
    settings = RenderSettings(blend=preset.blend, blur_length=fld.streak / max(1, frames),
                              blur_samples=preset.blur_samples if fld.streak > 0 else 1,
                              defocus_brighten=False, templates=fld.templates,
                              templates_digest=fld.templates_digest, coarse=preset.coarse)
    m = int(j.numel())
    atmosphere = None
    if fld.atmosphere is not None:
        step = fld.atmosphere.drift[0]
        atmosphere = fld.atmosphere.replace(drift=torch.stack((float(frame) * step,
                                                               float(frame + frames) * step)))
    if m == 0:
        return empty_particles(fld.frame, settings, preset.optics(), atmosphere)
    zeros = torch.zeros(m, 3, dtype=torch.float64)
    record = Particles(position=fld.positions(j, k, frame),
                       motion=(fld.step[j] * frames).double() * fld.quantum,
                       offset1=zeros, offset2=zeros.clone(), color=fld.color[j],
                       transparency=fld.transparency[j], template=fld.template[j],
                       rotation=fld.rotation[j], scale=fld.diameter[j],
                       defocus=torch.zeros(m, dtype=torch.long), frame=fld.frame,
                       settings=settings, optics=preset.optics(), atmosphere=atmosphere)
    return record.quantized()


def frame_particles(fld: Field, view: View, frame: int) -> Particles:
    """The particles drawn in one view at ``frame`` (one frame of a sequence, or a stereo view)."""
    j, k = fld.candidates(view, frame)
    return field_record(fld, j, k, frame)


def pair_trajectories(fld: Field, views: Sequence[View], frames: tuple[int, int]
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """The trajectories ``(j (M,), k (M, 3))`` drawn in frame 1 or frame 2 of a pair (the
    union, in canonical order: the order of the pair's record, :func:`field_pair_particles`)."""
    j1, k1 = fld.candidates(views[0], frames[0])
    j2, k2 = fld.candidates(views[1], frames[1])
    return _canonical(torch.cat((j1, j2)), torch.cat((k1, k2)))


def field_pair_particles(fld: Field, views: Sequence[View], frames: tuple[int, int]) -> Particles:
    """The particles drawn in frame 1 or frame 2 of a pair (the union, in canonical order):
    positions in frame 1, motion to frame 2."""
    j, k = pair_trajectories(fld, views, frames)
    return field_record(fld, j, k, frames[0], frames[1] - frames[0])


def field_for_pair(pair: FramePair, preset: FieldPreset, seed, *, world_up: str = "auto",
                   frame_rate: Optional[float] = None,
                   templates: Optional[TemplateLibrary] = None,
                   airlight: Optional[Sequence[float]] = None) -> Field:
    """The field of the pair's scene: reference frame and down axis from the pair's cameras,
    the frame rate from the preset or, where it sets none, ``frame_rate`` (the dataset's: its
    reader's :attr:`~weathergen.datasets.Dataset.frame_rate`; default the pair's own). An ``auto`` airlight is
    ``airlight`` (RGB in [0, 1]; a scene's, so that its pairs share it) or, without one, the
    pair's (:func:`pair_airlight`)."""
    frame, c1, c2 = reference_transforms(pair)
    down = world_down(c1.cpu(), c2.cpu(), world_up)
    rate = preset.frame_rate_for(pair.frame_rate if frame_rate is None else frame_rate)
    if airlight is None and preset.has_atmosphere and preset.airlight == "auto":
        airlight = pair_airlight(pair, preset.sky_distance)
    return make_field(preset, seed, down=down, frame_rate=rate, frame=frame, templates=templates,
                      airlight=airlight)


def pair_airlight(pair: FramePair, sky_distance: float = 1000.0) -> tuple[float, float, float]:
    """The ``auto`` airlight of a pair, from both its frames
    (:func:`~weathergen.engine.weather.atmosphere.estimate_airlight`), so that both frames share it."""
    light = estimate_airlight([pair.image1, pair.image2], [pair.depth1, pair.depth2],
                              pair.intrinsics, sky_distance)
    return tuple(float(c) for c in light)


def pair_views(pair: FramePair, device=None) -> tuple[View, View]:
    """The two views of a pair (reference transforms from :func:`reference_transforms`), on
    ``device`` (default: the CPU)."""
    _, c1, c2 = reference_transforms(pair)
    dev = torch.device("cpu") if device is None else torch.device(device)
    k = pair.intrinsics.double().to(dev)
    return (View(k, c1.to(dev), pair.depth1.to(dev)), View(k, c2.to(dev), pair.depth2.to(dev)))


def sample_field_particles(pair: FramePair, preset: FieldPreset, seed=0, *,
                           world_up: str = "auto", frame_rate: Optional[float] = None,
                           templates: Optional[TemplateLibrary] = None,
                           device=None, sample_on=None,
                           airlight: Optional[Sequence[float]] = None) -> Particles:
    """The record of one pair sampled from the field of seed ``seed`` (the *scene's* seed: pairs of
    one scene sampled with the same seed share their frames, see :func:`scene_seed`).

    Frame numbers are the pair's (``pair.id.frame`` and the next one), so that the field's time
    is the dataset's; ``frame_rate`` is the dataset's frames per second (see
    :func:`field_for_pair`; ``airlight``: an ``auto`` airlight given, e.g. the scene's). Returns
    a quantized record on ``device`` (default CPU). ``sample_on``: where the views' tests run
    (default: the CPU; the field's tile is drawn on the CPU either way, and on the CPU the record
    is the same bytes).
    """
    expect_kind(preset, FieldPreset, "sample_field_particles")
    check_pair_for_engine(pair)
    dev = resolve_device(device)
    fld = field_for_pair(pair, preset, seed, world_up=world_up, frame_rate=frame_rate,
                         templates=templates, airlight=airlight)
    n = int(pair.id.frame)
    views = pair_views(pair, resolve_device(sample_on))
    return field_pair_particles(fld, views, (n, n + 1)).to(dev)


def sample_weather(pair: FramePair, preset, seed=0, *, world_up: str = "auto",
                   frame_rate: Optional[float] = None,
                   templates: Optional[TemplateLibrary] = None, device=None, sample_on=None,
                   airlight: Optional[Sequence[float]] = None
                   ) -> Union[Particles, LayeredParticles]:
    """Sample a pair's particles with the preset's model: a field preset draws from the field of
    ``seed`` (:func:`sample_field_particles`; ``frame_rate``: the dataset's, needed unless the
    preset sets one; ``airlight``: the ``auto`` airlight of its atmosphere, default the pair's),
    a paper preset samples the pair (:func:`~weathergen.engine.sampling.pair.sample_particles`), a
    combined preset samples each layer (:func:`sample_layers`; ``seed`` may then be one seed per
    layer, ``templates`` is not taken). ``sample_on``: where the sampling arithmetic runs (see
    :func:`sample_particles` and :func:`sample_field_particles`; the same random numbers, from the
    seed's CPU generator)."""
    if isinstance(preset, CombinedPreset):
        if templates is not None:
            raise ConfigError("a combined preset's layers each load their own templates")
        return sample_layers(pair, preset, seed, world_up=world_up, frame_rate=frame_rate,
                             device=device, sample_on=sample_on, airlight=airlight)
    if isinstance(preset, FieldPreset):
        return sample_field_particles(pair, preset, seed, world_up=world_up,
                                      frame_rate=frame_rate, templates=templates, device=device,
                                      sample_on=sample_on, airlight=airlight)
    return sample_particles(pair, preset, seed, world_up=world_up, templates=templates,
                            device=device, sample_on=sample_on)


def sample_layers(pair: FramePair, preset: CombinedPreset, seed: Union[int, Sequence[int]] = 0, *,
                  world_up: str = "auto", frame_rate: Optional[float] = None,
                  device=None, sample_on=None,
                  airlight: Optional[Sequence[float]] = None) -> LayeredParticles:
    """The particles of every layer of a combined preset for one pair (``airlight``: the
    ``auto`` airlight of every layer's atmosphere; default the pair's, estimated once).

    ``seed`` is one seed per layer, or one seed from which each layer's is derived
    (:func:`~weathergen.engine.records.layered.layer_seed`, by the layer's name). Each layer is sampled as
    :func:`sample_weather` samples its preset alone with that seed, so a layer's particles depend
    neither on the other layers nor on their order. For a field layer the seed is its field's:
    pass each field layer a seed derived from its scene's (as ``weathergen render`` will) for the
    pairs of a scene to share their frames.
    """
    expect_kind(preset, CombinedPreset, "sample_layers")
    if isinstance(seed, torch.Generator):
        raise ConfigError("a combined preset takes an integer seed (or one per layer)")
    if isinstance(seed, int):
        seeds = tuple(layer_seed(seed, name) for name in preset.layer_names)
    else:
        seeds = tuple(int(s) for s in seed)
        if len(seeds) != len(preset.layers):
            raise ConfigError(f"{len(seeds)} seeds for the {len(preset.layers)} layers of "
                              f"{preset.name}")
    auto = [layer for layer in preset.layers if isinstance(layer, FieldPreset)
            and layer.has_atmosphere and layer.airlight == "auto"]
    if airlight is None and auto:
        airlight = pair_airlight(pair, max(layer.sky_distance for layer in auto))
    records = tuple(sample_weather(pair, layer, s, world_up=world_up, frame_rate=frame_rate,
                                   device=device, sample_on=sample_on, airlight=airlight)
                    for layer, s in zip(preset.layers, seeds))
    return LayeredParticles(records, preset.layer_names)
