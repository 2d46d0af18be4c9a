"""Particle sampling: a preset and a frame pair in, a :class:`Particles` record out.

Positions are drawn uniformly in the preset's sampling box (camera-1 coordinates) and kept when the
particle is visible in frame 1 (in front of the camera, inside the image, in front of the scene
depth) or, after the camera motion and its own motion, in frame 2. Candidates are drawn and tested
in vectorised batches whose size depends only on the requested count, on the CPU in float64 from
one explicitly seeded ``torch.Generator``: the same seed gives the same bytes on any machine and
with any number of workers. Most candidates usually lie outside both views, so a candidate's
motion is computed only when camera 1 sees it or when its motionless position lies within the
longest motion of camera 2's view cone (the particles are those of testing every candidate).
Positions and motions are rounded to their stored precision; a candidate the rounding moves out of
both views gives its place to the next kept one, so every stored particle is visible in frame 1 or
frame 2 (:func:`visibility`). The record is then moved to the requested device.

The count is the one the preset gives the pair's frame size (:func:`~weathergen.engine.weather.presets.
frame_scaling`: the preset's count on a 1024x436 frame, scaled by the frame's area elsewhere;
``size`` and the defocus radius scaled by its diagonal too where ``scale_size`` asks for it).

Depth-dependent properties use the particle's camera depth ``d`` in the frame that accepted it
(camera 1 where frame 1 sees it, else camera 2, as the paper's research code does: a particle that
only frame 2 shows is drawn at the size its frame-2 depth gives), fixed at sampling:

- footprint (pixels) ``size * min(1, 1 / (d * depth_decay))``, at least 1 (``size`` for the
  frame);
  ``scale = footprint / template resolution``;
- transparency (``transparency_mode = "depth"``): a hat in the tanh domain,
  ``t = 4/3 d - 1.5`` for ``d < 1.5`` else ``-4/3 d + 2.5``, ``θ = θ_scale (tanh t + 1) / 2``;
  (``"constant"``): ``θ = θ_scale``;
- defocus radius ``floor(s clip(a / (d - b), 0, 20) + 0.5)`` with ``b = 0.563``,
  ``a = 5 (0.75 - b)`` and ``s`` the frame's pixel scale (1 unless ``scale_size``); radii 0 and 1
  mean no blur.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Union

import torch

from ...errors import ConfigError
from ...framepair import FramePair
from ...geometry import WORLD_UP_AXES, invert_rigid, project, transform_points, up_direction
from ..common import NEAR, check_pair_for_engine, reference_transforms, resolve_device
from ..records.particles import Particles, quantize_field, empty_particles
from ..weather.presets import FrameScaling, Preset, frame_scaling
from ..records.settings import RenderSettings
from ..weather.templates import TemplateLibrary, load_templates

#: The named world-up settings; a direction "X,Y,Z" is accepted too (see :func:`world_down`).
WORLD_UP_CHOICES = ("auto",) + WORLD_UP_AXES
DEFOCUS_B = 0.563
DEFOCUS_A = 5 * (0.75 - DEFOCUS_B)
DEFOCUS_MAX = 20


def world_down(cam1_from_ref: torch.Tensor, cam2_from_ref: torch.Tensor,
               world_up: str = "auto") -> torch.Tensor:
    """Unit "down" vector of the reference frame. Shape: (4, 4) each -> (3,) float64.

    ``"auto"`` picks the reference axis nearest to the mean camera-up vector (camera −y) of both
    cameras; ``"+z"`` etc. name the up axis explicitly; ``"X,Y,Z"`` gives the up direction itself
    (a world that is not level). Raises :class:`ConfigError` naming ``world_up`` otherwise.
    """
    try:
        up = up_direction(world_up)
    except ConfigError as exc:
        raise ConfigError(f"world_up: {exc}") from None
    if up is not None:
        return -up
    # Row 1 of a cam_from_ref rotation is the camera's +y (down) axis in reference coordinates.
    mean_up = -(cam1_from_ref[1, :3] + cam2_from_ref[1, :3]).double().cpu()
    axis = int(mean_up.abs().argmax())
    sign = 1.0 if float(mean_up[axis]) >= 0 else -1.0
    down = torch.zeros(3, dtype=torch.float64)
    down[axis] = -sign
    return down


def _vertical_frame(down: torch.Tensor, cam1_from_ref: torch.Tensor) -> torch.Tensor:
    """A rotation whose columns are (x', y', z') with y' = down and x' as close as possible to
    camera 1's x axis, so that motion sampled in camera-like axes falls along the world's vertical.
    Shape: -> (3, 3) float64, ref_from_vertical.
    """
    cam_x = cam1_from_ref[0, :3].double().cpu()
    x = cam_x - (cam_x @ down) * down
    if float(x.norm()) < 1e-6:  # camera looks straight along the vertical: any x' will do
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        if abs(float(helper @ down)) > 0.9:
            helper = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
        x = helper - (helper @ down) * down
    x = x / x.norm()
    z = torch.linalg.cross(x, down)
    return torch.stack((x, down, z), dim=1)


def euler_rotations(angles: torch.Tensor) -> torch.Tensor:
    """Rotation matrices Rz Ry Rx from angles (radians). Shape: (N, 3) -> (N, 3, 3)."""
    cx, cy, cz = torch.cos(angles).unbind(-1)
    sx, sy, sz = torch.sin(angles).unbind(-1)
    one, zero = torch.ones_like(cx), torch.zeros_like(cx)
    rx = torch.stack((one, zero, zero, zero, cx, -sx, zero, sx, cx), -1).view(-1, 3, 3)
    ry = torch.stack((cy, zero, sy, zero, one, zero, -sy, zero, cy), -1).view(-1, 3, 3)
    rz = torch.stack((cz, -sz, zero, sz, cz, zero, zero, zero, one), -1).view(-1, 3, 3)
    return rz @ ry @ rx


def _visible(points_cam: torch.Tensor, intrinsics: torch.Tensor, depth: torch.Tensor
             ) -> torch.Tensor:
    """Which camera points are in front of the camera, inside the image and in front of the
    scene surface at their (nearest) pixel. Shape: (N, 3), (3, 3), (1, H, W) -> (N,) bool."""
    h, w = depth.shape[-2:]
    pix, z = project(points_cam, intrinsics)
    ok = (z > NEAR) & (pix[:, 0] >= -0.5) & (pix[:, 0] < w - 0.5) \
        & (pix[:, 1] >= -0.5) & (pix[:, 1] < h - 0.5)
    col = torch.floor(pix[:, 0] + 0.5).clamp(0, w - 1).long()
    row = torch.floor(pix[:, 1] + 0.5).clamp(0, h - 1).long()
    scene = depth[0, row, col].double()
    return ok & (z < scene)


def _view_cone(intrinsics: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Inward unit normals of the four planes through the camera centre and the image border
    (pixel edges at -0.5 and W - 0.5, H - 0.5) that :func:`_visible` tests. Shape: -> (4, 3)."""
    inv = torch.linalg.inv(intrinsics.double().cpu())

    def ray(x, y):
        return inv @ torch.tensor([x, y, 1.0], dtype=torch.float64)

    x0, x1, y0, y1 = -0.5, width - 0.5, -0.5, height - 0.5
    centre = ray((x0 + x1) / 2, (y0 + y1) / 2)
    corners = [ray(x0, y0), ray(x1, y0), ray(x1, y1), ray(x0, y1)]
    normals = []
    for a, b in zip(corners, corners[1:] + corners[:1]):
        n = torch.linalg.cross(a, b)
        n = n / n.norm()
        normals.append(n if float(n @ centre) > 0 else -n)
    return torch.stack(normals)


def _within_reach(points_cam: torch.Tensor, cone: torch.Tensor, reach: float) -> torch.Tensor:
    """Which camera points lie within ``reach`` of the view cone ``cone`` (see
    :func:`_view_cone`) in front of :data:`NEAR`: a point moved by at most ``reach`` can only
    become visible when this holds (with a margin for rounding). Shape: (N, 3) -> (N,) bool."""
    size = float(points_cam.abs().max()) if points_cam.numel() else 0.0
    slack = reach * (1 + 1e-6) + 1e-6 * (1 + size)
    inside = (points_cam @ cone.T >= -slack).all(1)
    return inside & (points_cam[:, 2] > NEAR - slack)


def transparency_hat(d: torch.Tensor) -> torch.Tensor:
    """The depth hat in [0, 1] (peak at d = 1.5). Shape: any -> same."""
    t = torch.where(d < 1.5, 4.0 / 3.0 * d - 1.5, -4.0 / 3.0 * d + 2.5)
    return (torch.tanh(t) + 1) / 2


def defocus_radius(d: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """Disc-blur radius in pixels for camera depth ``d`` on a frame whose lengths in pixels are
    ``scale`` times a 1024x436 frame's. Shape: any -> same, int64."""
    safe = torch.where(d > DEFOCUS_B, d - DEFOCUS_B, torch.ones_like(d))
    r = torch.where(d > DEFOCUS_B, DEFOCUS_A / safe, torch.zeros_like(d))
    return torch.floor(r.clamp(0, DEFOCUS_MAX) * scale + 0.5).long()


# -- colour --------------------------------------------------------------------------------

def rgb_to_hls(rgb: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 1] to HLS (hue in [0, 1) turns, lightness, saturation). Shape: (..., 3)."""
    r, g, b = rgb.unbind(-1)
    maxc, minc = rgb.max(-1).values, rgb.min(-1).values
    light = (maxc + minc) / 2
    span = maxc - minc
    grey = span <= 0
    safe_span = torch.where(grey, torch.ones_like(span), span)
    denom = torch.where(light <= 0.5, maxc + minc, 2.0 - maxc - minc)
    sat = torch.where(grey, torch.zeros_like(span),
                      span / torch.where(denom > 0, denom, torch.ones_like(denom)))
    rc, gc, bc = (maxc - r) / safe_span, (maxc - g) / safe_span, (maxc - b) / safe_span
    hue = torch.where(r == maxc, bc - gc, torch.where(g == maxc, 2.0 + rc - bc, 4.0 + gc - rc))
    hue = torch.where(grey, torch.zeros_like(hue), torch.remainder(hue / 6.0, 1.0))
    return torch.stack((hue, light, sat), -1)


def hls_to_rgb(hls: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_hls`. Shape: (..., 3) -> (..., 3)."""
    hue, light, sat = hls.unbind(-1)
    m2 = torch.where(light <= 0.5, light * (1.0 + sat), light + sat - light * sat)
    m1 = 2.0 * light - m2

    def channel(h):
        h = torch.remainder(h, 1.0)
        return torch.where(h < 1 / 6, m1 + (m2 - m1) * h * 6.0,
                           torch.where(h < 0.5, m2,
                                       torch.where(h < 2 / 3, m1 + (m2 - m1) * (2 / 3 - h) * 6.0,
                                                   m1)))

    rgb = torch.stack((channel(hue + 1 / 3), channel(hue), channel(hue - 1 / 3)), -1)
    return torch.where((sat == 0)[..., None], light[..., None].expand_as(rgb), rgb)


# -- sampling ------------------------------------------------------------------------------

def cpu_generator(seed: Union[int, torch.Generator]) -> torch.Generator:
    """A CPU generator seeded with ``seed`` (an int), or ``seed`` itself (a CPU generator).
    Raises ConfigError otherwise."""
    if isinstance(seed, torch.Generator):
        if seed.device.type != "cpu":
            raise ConfigError("the sampling generator must be a CPU torch.Generator")
        return seed
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"seed {seed!r}: must be an integer")
    g = torch.Generator(device="cpu")
    g.manual_seed(int(seed))
    return g


def expect_kind(preset, kind: type, call: str) -> None:
    """Refuse, in one line, a preset of another model than ``call`` samples (a field or combined
    preset given to the paper's sampler, or the other way round), naming the call that takes it."""
    if not isinstance(preset, kind):
        what = {"Preset": "a paper preset", "FieldPreset": "a weather-field preset",
                "CombinedPreset": "a combined preset"}.get(type(preset).__name__, repr(preset))
        raise ConfigError(f"{getattr(preset, 'name', preset)!s} is {what}, which {call} does not "
                          "take: sample any preset with sample_weather(pair, preset, seed), or "
                          "render it in one call with Weather(preset, seed).render(pair)")


def sample_particles(pair: FramePair, preset: Preset, seed: Union[int, torch.Generator] = 0, *,
                     world_up: str = "auto", templates: Optional[TemplateLibrary] = None,
                     device=None, max_candidates_factor: int = 500,
                     sample_on=None) -> Particles:
    """Sample the preset's count of particles for one frame pair (``preset.count`` on a 1024x436
    frame; on other frame sizes as :func:`~weathergen.engine.weather.presets.frame_scaling` says).

    Shape: uses pair.depth1/depth2 (1, H, W), intrinsics (3, 3), the pair's poses (4, 4).
    Returns a quantized :class:`Particles` record on ``device`` (default CPU).
    ``world_up`` says which reference axis points up (see :func:`world_down`). Raises ConfigError
    when fewer than ``count`` visible positions turn up among ``max_candidates_factor * count``
    candidates (the sampling box lies behind the scene or outside the view).

    ``sample_on``: the device of the arithmetic (default: the CPU). The random numbers are always
    drawn from the seed's CPU generator, in the same order, and moved there; on the CPU the
    record is the same bytes either way. On a GPU (the device a batch is rendered on) the
    visibility tests run where the depth maps already are; the record then equals the CPU's
    except where a candidate lies within float64 rounding of an image border or the scene
    surface (see docs/engine.md, "Sampling", on the render's device).
    """
    expect_kind(preset, Preset, "sample_particles")
    check_pair_for_engine(pair)
    dev = resolve_device(device)
    on = resolve_device(sample_on)
    gen = cpu_generator(seed)
    lib = templates if templates is not None else load_templates(preset.templates)
    cams = _Cameras.of(pair, on)
    settings = RenderSettings.from_preset(preset, lib)
    scaling = frame_scaling(preset, cams.depth1.shape[-2], cams.depth1.shape[-1])
    n = scaling.count
    if n == 0:
        return empty_particles(cams.frame, settings).to(dev)
    candidates = _Candidates(cams, preset, n, gen, world_up=world_up,
                             limit=max_candidates_factor * n)
    position, motion = candidates.visible_particles()
    # Per-particle appearance, drawn for exactly n particles after the positions.
    u = torch.rand(n, 4, generator=gen, dtype=torch.float64).to(on)
    template = torch.randint(0, lib.count, (n,), generator=gen).to(on)
    scale, theta, defocus = _depth_looks(cams, position, motion, preset, scaling, lib.resolution)
    zeros = torch.zeros(n, 3, dtype=torch.float64, device=on)
    record = Particles(position=position, motion=motion, offset1=zeros, offset2=zeros.clone(),
                       color=_jittered_colors(preset, u[:, 1:4]), transparency=theta,
                       template=template, rotation=u[:, 0] * 2 * math.pi, scale=scale,
                       defocus=defocus, frame=cams.frame, settings=settings)
    return record.quantized().to(dev)


@dataclass
class _Cameras:
    """A pair's cameras on the device of the sampling arithmetic: the reference ``frame``
    (``"world"`` or ``"camera1"``), both cameras' transforms from it and camera 1's inverse
    (4, 4) float64, the intrinsics (3, 3) float64, the depth maps (1, H, W)."""

    frame: str
    cam1_from_ref: torch.Tensor
    cam2_from_ref: torch.Tensor
    ref_from_cam1: torch.Tensor
    k: torch.Tensor
    depth1: torch.Tensor
    depth2: torch.Tensor

    @classmethod
    def of(cls, pair: FramePair, on: torch.device) -> "_Cameras":
        frame, cam1_from_ref, cam2_from_ref = reference_transforms(pair)
        cam1_from_ref, cam2_from_ref = cam1_from_ref.to(on), cam2_from_ref.to(on)
        return cls(frame, cam1_from_ref, cam2_from_ref, invert_rigid(cam1_from_ref),
                   pair.intrinsics.double().to(on), pair.depth1.to(on), pair.depth2.to(on))

    def visible_either(self, pos_ref: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
        """Which particles at ``pos_ref`` moving by ``motion`` (reference frame) frame 1 or
        frame 2 shows. Shape: (N, 3) each -> (N,) bool."""
        return _visible(transform_points(self.cam1_from_ref, pos_ref), self.k, self.depth1) \
            | _visible(transform_points(self.cam2_from_ref, pos_ref + motion), self.k, self.depth2)


class _Candidates:
    """Candidate particles of one pair, drawn in batches from the seed's generator: positions
    uniform in the preset's sampling box (camera-1 coordinates), motions ``motion_y`` down the
    world's vertical, turned by up to ``motion_angle_jitter`` degrees about each axis and scaled by
    up to ``1 ± motion_scale_jitter``; kept where frame 1 or, after the camera motion and their
    own, frame 2 shows them. ``limit``: the most candidates drawn before giving up."""

    def __init__(self, cams: _Cameras, preset: Preset, n: int, gen: torch.Generator, *,
                 world_up: str, limit: int):
        on = cams.k.device
        self.cams, self.preset, self.n, self.gen, self.limit = cams, preset, n, gen, limit
        self.ref_from_vertical = _vertical_frame(
            world_down(cams.cam1_from_ref, cams.cam2_from_ref, world_up), cams.cam1_from_ref).to(on)
        self.lo = torch.tensor([preset.volume_x[0], preset.volume_y[0], preset.volume_z[0]],
                               dtype=torch.float64, device=on)
        self.hi = torch.tensor([preset.volume_x[1], preset.volume_y[1], preset.volume_z[1]],
                               dtype=torch.float64, device=on)
        self.angle = math.radians(preset.motion_angle_jitter)
        self.base = torch.tensor([0.0, preset.motion_y, 0.0], dtype=torch.float64, device=on)
        self.cone2 = _view_cone(cams.k, cams.depth2.shape[-2], cams.depth2.shape[-1]).to(on)
        # the longest motion (rotations keep lengths; a camera's scale, if any, stretches it)
        self.reach = abs(preset.motion_y) * (1 + preset.motion_scale_jitter) \
            * float(torch.linalg.matrix_norm(cams.cam2_from_ref[:3, :3].cpu(), ord=2))
        self.batch = min(max(4096, 4 * n), 1 << 18)  # depends on the count only: reproducible
        self.tried = 0

    def visible_particles(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The first ``n`` kept candidates, positions and motions rounded to their stored
        precision, every one still visible in frame 1 or frame 2. Shape: -> (n, 3) each."""
        n, on = self.n, self.cams.k.device
        accepted_pos, accepted_motion = torch.zeros(0, 3, dtype=torch.float64, device=on), \
            torch.zeros(0, 3, dtype=torch.float64, device=on)
        while True:
            while accepted_pos.shape[0] < n:
                pos_b, motion_b = self.draw(accepted_pos.shape[0])
                accepted_pos = torch.cat((accepted_pos, pos_b))
                accepted_motion = torch.cat((accepted_motion, motion_b))
            # Round to the stored precision first, so that the depth-dependent properties
            # follow from exactly the positions a saved record holds. A candidate that the
            # rounding moves out of both views (it lay on the image border or the scene surface)
            # gives its place to the next accepted one, so that every stored particle is visible
            # in frame 1 or frame 2 (rare: about one in several thousand particles).
            position = quantize_field("position", accepted_pos[:n]).double().to(on)
            motion = quantize_field("motion", accepted_motion[:n]).double().to(on)
            ok = self.cams.visible_either(position, motion)
            if bool(ok.all()):
                return position, motion
            keep = torch.cat((ok, torch.ones(accepted_pos.shape[0] - n, dtype=torch.bool,
                                             device=on)))
            accepted_pos, accepted_motion = accepted_pos[keep], accepted_motion[keep]

    def draw(self, have: int) -> tuple[torch.Tensor, torch.Tensor]:
        """One batch of candidates: the positions (reference frame) and motions of those
        visible in frame 1 or, after the camera motion and their own, in frame 2 (``have``: how
        many were kept so far, for the error). Shape: -> (M, 3) each."""
        cams, preset = self.cams, self.preset
        if self.tried >= self.limit:
            raise ConfigError(
                f"could place only {have} of {self.n} particles: the sampling box "
                f"x{list(preset.volume_x)} y{list(preset.volume_y)} z{list(preset.volume_z)} "
                "is mostly hidden behind the scene or outside the view (check the depth scale "
                "or the preset's volume_* keys)")
        u = torch.rand(self.batch, 7, generator=self.gen, dtype=torch.float64).to(cams.k.device)
        self.tried += self.batch
        pos_cam1 = self.lo + (self.hi - self.lo) * u[:, :3]
        pos_ref = transform_points(cams.ref_from_cam1, pos_cam1)
        vis1 = _visible(pos_cam1, cams.k, cams.depth1)
        # Most candidates lie outside both views. Frame 2 can only see one whose motionless
        # position is within the longest motion of its view cone, so only those and the ones
        # frame 1 sees need their motion (the same particles as testing every candidate).
        near2 = _within_reach(transform_points(cams.cam2_from_ref, pos_ref), self.cone2,
                              self.reach)
        cand = torch.nonzero(vis1 | near2).squeeze(1)
        motion = self.motions(u[cand])
        pos_ref = pos_ref[cand]
        vis = vis1[cand] | _visible(transform_points(cams.cam2_from_ref, pos_ref + motion),
                                    cams.k, cams.depth2)
        return pos_ref[vis], motion[vis]

    def motions(self, u: torch.Tensor) -> torch.Tensor:
        """The candidates' motions (reference frame) from their uniform numbers: columns 3-5 the
        jitter angles, column 6 the scale. Shape: (M, 7) -> (M, 3)."""
        rot = euler_rotations((2 * u[:, 3:6] - 1) * self.angle)
        factor = 1 + (2 * u[:, 6] - 1) * self.preset.motion_scale_jitter
        motion_vertical = (rot @ self.base) * factor[:, None]
        return motion_vertical @ self.ref_from_vertical.T


def _depth_looks(cams: _Cameras, position: torch.Tensor, motion: torch.Tensor, preset: Preset,
                 scaling: FrameScaling, resolution: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The looks that follow from each particle's camera depth in the frame that accepted it
    (frame 1 where it sees the particle, else frame 2; see the module doc): the template scale
    (footprint pixels / template resolution), the transparency θ and the defocus radius (pixels).
    ``scaling``: the preset's :class:`~weathergen.engine.weather.presets.FrameScaling` for the frame.
    Shape: (n, 3) each -> (n,) float64, (n,) float64, (n,) int64."""
    x1 = transform_points(cams.cam1_from_ref, position)
    z2 = transform_points(cams.cam2_from_ref, position + motion)[:, 2]
    d = torch.where(_visible(x1, cams.k, cams.depth1), x1[:, 2], z2)
    footprint = (scaling.size * torch.clamp(1.0 / (d * preset.depth_decay), max=1.0)).clamp(min=1.0)
    scale = footprint / resolution
    if preset.transparency_mode == "constant":
        theta = torch.full_like(d, preset.transparency)
    else:
        theta = preset.transparency * transparency_hat(d)
    defocus = defocus_radius(d, scaling.pixel_scale) if preset.defocus else \
        torch.zeros(d.shape[0], dtype=torch.int64, device=d.device)
    return scale, theta, defocus


def _jittered_colors(preset: Preset, u: torch.Tensor) -> torch.Tensor:
    """The preset's colour jittered in HLS by up to ``hue_jitter`` degrees, ``lightness_jitter``
    and ``saturation_jitter``, from uniform numbers ``u`` (hue, lightness, saturation).
    Shape: (n, 3) -> (n, 3) RGB in [0, 1], float64."""
    hls = rgb_to_hls(torch.tensor(preset.color, dtype=torch.float64, device=u.device) / 255.0) \
        .expand(u.shape[0], 3)
    jitter = (2 * u - 1) * torch.tensor(
        [preset.hue_jitter / 360.0, preset.lightness_jitter, preset.saturation_jitter],
        dtype=torch.float64, device=u.device)
    hls = hls + jitter
    hls = torch.stack((torch.remainder(hls[:, 0], 1.0), hls[:, 1].clamp(0, 1),
                       hls[:, 2].clamp(0, 1)), -1)
    return hls_to_rgb(hls).clamp(0, 1)


def visibility(pair: FramePair, particles: Particles) -> tuple[torch.Tensor, torch.Tensor]:
    """Which particle centres each frame shows in front of the scene surface: the test sampling
    keeps a candidate by (:func:`_visible`; frame 1 sees ``P + δ1``, frame 2 ``P + δ1 + M + δ2``).

    Every sampled particle is visible in frame 1 or in frame 2 (or both). Shape: -> two (N,) bool.
    """
    _, cam1_from_ref, cam2_from_ref = reference_transforms(pair)
    start = (particles.position + particles.offset1).double().cpu()
    end = start + (particles.motion + particles.offset2).double().cpu()
    k = pair.intrinsics.double().cpu()
    masks = []
    for cam_from_ref, points, depth in ((cam1_from_ref, start, pair.depth1),
                                        (cam2_from_ref, end, pair.depth2)):
        camera = transform_points(cam_from_ref.double().cpu(), points)
        masks.append(_visible(camera, k, depth.cpu()))
    return masks[0], masks[1]


def visible_counts(pair: FramePair, particles: Particles) -> tuple[int, int]:
    """How many particle centres each frame shows in front of the scene surface
    (see :func:`visibility`)."""
    vis1, vis2 = visibility(pair, particles)
    return int(vis1.sum()), int(vis2.sum())
