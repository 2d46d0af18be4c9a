"""The atmosphere of weather fields: Koschmieder's law per pixel, the airlight, the heterogeneous
density (mean, anchoring in the world, over frames and stereo), the integration's error bound,
particles seen through the air, storage and gradients."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from engine_scenes import plane_pair, pose, rotation
from weathergen.engine import (LayeredParticles, Particles, load_preset, render_pair,
                               sample_weather)
from weathergen.engine.rendering.transmittance import Air
from weathergen.engine.weather.atmosphere import (LATTICE, RAY_ANGLE, RAY_STEP, Atmosphere,
                                                  density_lattice, estimate_airlight,
                                                  rain_extinction, ray_norms, sample_lattice,
                                                  snow_extinction)
from weathergen.engine.sampling.field import sample_field_particles
from weathergen.engine.rendering.renderer import render, render_view
from weathergen.engine.sampling.pair import reference_transforms
from weathergen.engine.rendering.stereo import stereo_view
from weathergen.engine.views import View
from weathergen.errors import ConfigError
from weathergen.framepair import FramePair, PairId


def density_at(atmosphere: Atmosphere, points: torch.Tensor, frame: int = 0) -> torch.Tensor:
    """ρ at reference points in the pair's frame ``frame`` (0 or 1). Shape: (..., 3) ->
    (...) float64."""
    if atmosphere.uniform:
        return torch.ones(points.shape[:-1], dtype=torch.float64, device=points.device)
    drifted = points.double() - atmosphere.drift[frame].to(points.device)
    lattice = atmosphere.lattice(torch.float64, points.device)
    return sample_lattice(lattice, drifted / atmosphere.voxel).double()


# -- the fine reference the integration is tested against ------------------------------------

class AirView:
    """One atmosphere seen by one camera in frame ``frame`` (0 or 1) of its pair: the optical
    depth along any ray of the view (:meth:`optical_depth`), as a render integrates it.

    Shape: intrinsics (3, 3), cam_from_ref (4, 4), size (H, W).
    """

    def __init__(self, atmosphere: Atmosphere, intrinsics: torch.Tensor,
                 cam_from_ref: torch.Tensor, size: tuple[int, int], frame: int, device=None):
        self.atmosphere = atmosphere
        self.frame = int(frame)
        self.air = Air([[atmosphere]], intrinsics[None], cam_from_ref[None], size, [frame],
                       device)
        self.intrinsics = intrinsics.detach().double().to(self.air.device)
        self.cam_from_ref = self.air.cam_from_ref[0]
        focal = float(torch.sqrt(self.intrinsics[0, 0] * self.intrinsics[1, 1]))
        self.step = max(1, min(RAY_STEP, int(math.floor(focal * RAY_ANGLE))))

    def distances(self, depth: torch.Tensor) -> torch.Tensor:
        """Every pixel's ray length, at most ``sky_distance``. Shape: (1, H, W) -> (1, H, W)."""
        height, width = depth.shape[-2:]
        dev = self.air.device
        v = torch.arange(height, dtype=torch.float64, device=dev)[:, None]
        u = torch.arange(width, dtype=torch.float64, device=dev)[None, :]
        return (depth.to(dev).double() * ray_norms(self.air.camera[0], u, v)) \
            .clamp(max=self.atmosphere.sky_distance)

    def optical_depth(self, u: torch.Tensor, v: torch.Tensor, distance: torch.Tensor
                      ) -> torch.Tensor:
        """τ along the rays through ``(u, v)`` up to ``distance``. Shape: any (same) -> same,
        float64."""
        zero = torch.zeros((), dtype=torch.long, device=self.air.device)
        return self.air.optical_depth(zero, u, v, distance)


def reference_optical_depth(air: AirView, u: torch.Tensor, v: torch.Tensor,
                            distance: torch.Tensor, samples: int) -> torch.Tensor:
    """τ by the midpoint rule with ``samples`` equal intervals along each point's own ray (no
    coarse rays): the fine reference the integration is tested against.
    Shape: any (same) shape -> that shape, float64."""
    atm = air.atmosphere
    length = distance.double().clamp(0, atm.sky_distance)
    if atm.uniform:
        return atm.extinction * length
    k = air.intrinsics
    cy = (v.double() - k[1, 2]) / k[1, 1]
    cx = (u.double() - k[0, 2] - k[0, 1] * cy) / k[0, 0]
    ray = torch.stack((cx, cy, torch.ones_like(cx)), -1)
    ray = ray / ray.norm(dim=-1, keepdim=True)
    rot, trans = air.cam_from_ref[:3, :3], air.cam_from_ref[:3, 3]
    direction = (ray[..., :, None] * rot).sum(-2)
    origin = -(trans[:, None] * rot).sum(0) - atm.drift[air.frame].to(length.device)
    lattice = atm.lattice(torch.float64, length.device)
    total = torch.zeros_like(length)
    chunk = max(1, (1 << 22) // max(1, length.numel()))
    for j0 in range(0, samples, chunk):
        fractions = (torch.arange(j0, min(samples, j0 + chunk), dtype=torch.float64,
                                  device=length.device) + 0.5) / samples
        s = length[..., None] * fractions                                    # (..., J)
        points = origin + direction[..., None, :] * s[..., None]
        total = total + sample_lattice(lattice, points / atm.voxel).double().sum(-1)
    return atm.extinction * length * total / samples


RATE = 10.0
#: The integration's stated bounds on |t − t_ref| (docs/engine.md, "The atmosphere"): rays to
#: surfaces within 200 m, and every ray (the sky's are 1000 m long).
BOUND_SURFACES = 0.001
BOUND = 0.006


def air_preset(name: str = "fog-moderate", **over):
    return load_preset(name, {k: str(v) if not isinstance(v, str) else v
                              for k, v in over.items()})


def uniform_fog(visibility: float = 50.0, airlight=(200, 180, 160)):
    return air_preset(heterogeneity=0, visibility=visibility,
                      airlight=",".join(str(c) for c in airlight))


def tilted_pair(height=30, width=40, dtype=torch.float64, world=True) -> FramePair:
    """A plane whose camera depth grows down the image (4 to 40), a second camera moved and
    turned a little."""
    pair = plane_pair(height, width, world=world, dtype=dtype,
                      cam2_from_world=pose(rotation(yaw_deg=2.0), (0.3, 0.0, 0.5)))
    rows = torch.linspace(4.0, 40.0, height, dtype=dtype)[:, None].expand(height, width)
    return dataclasses.replace(pair, depth1=rows[None].clone(), depth2=(rows[None] * 1.1))


def distances(depth: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """Hand-computed ray lengths: depth × |K⁻¹ (u, v, 1)|. Shape: (1, H, W) -> (1, H, W)."""
    h, w = depth.shape[-2:]
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                          indexing="ij")
    x, y = (u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1]
    return depth.double() * torch.sqrt(x ** 2 + y ** 2 + 1)


def test_extinction_of_visibility_and_of_precipitation():
    beta = -math.log(0.05) / 300.0
    assert load_preset("fog-moderate").extinction == pytest.approx(beta, rel=1e-12)
    # rain: 2.24 C^0.75 per km, C = R / (3.6 · 6) g/m³ (hand-computed for 25 mm/h)
    c = 25 / 21.6
    assert rain_extinction(25.0) == pytest.approx(2.24e-3 * c ** 0.75, rel=1e-12)
    assert rain_extinction(25.0) == pytest.approx(0.0024996, rel=1e-4)
    # snow: 10.36 C^0.7776 per km, C = S / 3.6 g/m³
    assert snow_extinction(3.0) == pytest.approx(10.36e-3 * (3 / 3.6) ** 0.7776, rel=1e-12)
    # per mm/h, snow extinguishes far more than rain
    for rate in (0.5, 1.0, 3.0, 10.0):
        assert snow_extinction(rate) > 10 * rain_extinction(rate)
    assert rain_extinction(0) == snow_extinction(0) == 0
    # the ladder: visibilities fall with the rate, snow's below rain's
    vis = {n: -math.log(0.05) / load_preset(n).extinction
           for n in ("rain-light", "rain-moderate", "rain-heavy", "snow-light", "snow-moderate",
                     "snow-heavy")}
    assert vis["rain-light"] > vis["rain-moderate"] > vis["rain-heavy"] > 1000
    assert vis["snow-light"] > vis["snow-moderate"] > vis["snow-heavy"]
    assert 1000 < vis["snow-light"] and vis["snow-heavy"] < 400      # NWS: heavy snow < 400 m
    assert load_preset("sparks-heavy").extinction == 0


def test_fog_ladder_is_visibility_1000_300_100():
    for name, visibility in (("fog-light", 1000), ("fog-moderate", 300), ("fog-heavy", 100),
                             ("mist", 2500)):
        preset = load_preset(name)
        assert preset.visibility == visibility and preset.density == 0
        assert preset.extinction == pytest.approx(-math.log(0.05) / visibility)


@pytest.mark.parametrize("world", [True, False])
def test_koschmieder_on_a_uniform_depth_plane_per_pixel_in_both_frames(world):
    pair = plane_pair(24, 32, depth=30.0, world=world, dtype=torch.float64,
                      cam2_from_world=pose(rotation(pitch_deg=3.0), (0.2, 0.1, 1.0)))
    preset = uniform_fog(50.0)
    record = sample_weather(pair, preset, 0, frame_rate=RATE)
    assert record.count == 0 and record.atmosphere is not None
    out = render_pair(pair, record)
    beta = -math.log(0.05) / 50.0
    light = torch.tensor([200, 180, 160], dtype=torch.float64) / 255
    for image, opacity, depth in ((pair.image1, out.opacity1, pair.depth1),
                                  (pair.image2, out.opacity2, pair.depth2)):
        expected = 1 - torch.exp(-beta * distances(depth, pair.intrinsics))
        assert torch.allclose(opacity[0], expected, rtol=0, atol=1e-15)
        t = 1 - expected
        fogged = image * t + light[:, None, None] * (1 - t)
        assert torch.allclose(out.image1[0] if image is pair.image1 else out.image2[0], fogged,
                              rtol=0, atol=1e-15)
    # at the principal point the ray length is the depth: 1 − t = 1 − exp(−β d) exactly
    c = out.opacity1[0, 0]
    centre = (1 - torch.exp(torch.tensor(-beta * 30.0, dtype=torch.float64)))
    assert abs(float(c[11:13, 15:17].max() - centre)) < 0.01       # near the centre
    # float32 frames: the same to float precision
    out32 = render_pair(plane_pair(24, 32, depth=30.0, world=world), record)
    expected = 1 - torch.exp(-beta * distances(pair.depth1, pair.intrinsics))
    assert torch.allclose(out32.opacity1[0].double(), expected, rtol=0, atol=1e-6)


def test_koschmieder_on_a_tilted_plane_per_pixel_in_both_frames():
    pair = tilted_pair()
    out = render_pair(pair, sample_weather(pair, uniform_fog(80.0), 0, frame_rate=RATE))
    beta = -math.log(0.05) / 80.0
    for opacity, depth in ((out.opacity1, pair.depth1), (out.opacity2, pair.depth2)):
        expected = 1 - torch.exp(-beta * distances(depth, pair.intrinsics))
        assert torch.allclose(opacity[0], expected, rtol=0, atol=1e-15)
        assert float(expected.max() - expected.min()) > 0.3          # the depth matters


def test_sky_pixels_reach_the_airlight_for_heavy_fog():
    pair = plane_pair(20, 24, depth=30.0, dtype=torch.float64)
    sky = pair.depth1.clone()
    sky[..., :8, :] = 1000.0                      # the far depth readers give the sky
    pair = dataclasses.replace(pair, depth1=sky, depth2=sky.clone())
    record = sample_weather(pair, load_preset("fog-heavy"), 0, frame_rate=RATE)
    out = render_pair(pair, record)
    light = record.atmosphere.airlight
    top = out.image1[0, :, :8]
    assert float((top - light[:, None, None]).abs().max()) <= 0.01 * float(light.max())
    assert float(out.opacity1[0, 0, :8].min()) > 0.99


def test_auto_airlight_is_the_far_bright_pixels_colour_nearly_grey_and_shared_by_the_pair():
    """The farthest 5 % of both frames' pixels, the brightest quarter of them, a quarter of
    their colour kept, and no darker than the frames' white point."""
    h, w = 20, 20
    image1 = torch.full((3, h, w), 0.2, dtype=torch.float64)
    image2 = image1.clone()
    depth = torch.full((1, h, w), 5.0, dtype=torch.float64)
    depth[..., :2, :] = 1000.0                     # the sky: 10 % of the pixels
    image1[:, :2, :] = torch.tensor([0.5, 0.7, 1.0])[:, None, None]
    image1[:, 0, :5] = 1.0                          # a few white pixels among the far ones
    k = torch.tensor([[20.0, 0, 9.5], [0, 20.0, 9.5], [0, 0, 1]], dtype=torch.float64)
    light = estimate_airlight([image1, image2], [depth, depth], k)
    # the farthest 5 % of both frames' 800 pixels: 40, the 10 brightest of them
    far = torch.cat((image1[:, :2].reshape(3, -1), image2[:, :2].reshape(3, -1)), 1)
    lum = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)
    # distance ties (the sky at 1000) fall to the pixel order: frame 1's sky rows first
    dist = distances(depth, k).clamp(max=1000.0).reshape(-1)
    order = torch.argsort(torch.cat((dist, dist)), descending=True, stable=True)[:40]
    colours = torch.cat((image1.reshape(3, -1), image2.reshape(3, -1)), 1)[:, order]
    chosen = torch.argsort((lum[:, None] * colours).sum(0), descending=True, stable=True)[:10]
    mean = colours[:, chosen].mean(1)
    grey = (lum * mean).sum()
    assert torch.allclose(light, grey + 0.25 * (mean - grey), atol=1e-12)
    assert float(far.max()) >= float(light.max())
    # no sky, dark far walls: the airlight is lifted to the frames' white point (99th
    # percentile of the luminance), keeping its colour
    dark = image1.clone()
    dark[:, :2, :] = 0.1
    dark[:, 10:, :4] = 0.9                     # bright near surfaces: 20 % of frame 1's pixels
    lifted = estimate_airlight([dark, image2], [depth, depth], k)
    assert float((lum * lifted).sum()) == pytest.approx(0.9, abs=1e-12)
    assert torch.allclose(lifted, torch.full((3,), 0.9, dtype=torch.float64), atol=1e-12)
    # a pair's record holds it, and both frames use it
    pair = FramePair(id=PairId("synthetic", "test", "sky", 1), image1=image1.float(),
                     image2=image2.float(), depth1=depth.float(), depth2=depth.float(),
                     intrinsics=k, cam2_from_cam1=torch.eye(4, dtype=torch.float64),
                     cam1_from_world=torch.eye(4, dtype=torch.float64),
                     cam2_from_world=torch.eye(4, dtype=torch.float64))
    record = sample_weather(pair, load_preset("fog-heavy"), 0, frame_rate=RATE)
    assert torch.allclose(record.atmosphere.airlight, light.float().double(), atol=1e-6)
    given = sample_weather(pair, load_preset("fog-heavy"), 0, frame_rate=RATE,
                           airlight=(0.1, 0.2, 0.3))
    assert given.atmosphere.airlight.tolist() == pytest.approx([0.1, 0.2, 0.3])


def test_density_lattice_has_mean_one_and_the_stated_range():
    for h in (0.0, 0.3, 0.5, 0.9):
        rho = density_lattice(7, h)
        assert rho.shape == (LATTICE,) * 3
        assert float(rho.mean()) == pytest.approx(1.0, abs=1e-12)
        assert float(rho.min()) >= 1 - h - 1e-12 and float(rho.max()) <= 1 + h + 1e-12
    rho = density_lattice(7, 0.5)
    assert float(rho.max()) == pytest.approx(1.5) or float(rho.min()) == pytest.approx(0.5)
    assert not torch.equal(density_lattice(8, 0.5), rho)          # another seed, other banks
    assert torch.equal(density_lattice(7, 0.5), rho)              # the same seed, the same


def test_heterogeneous_fog_keeps_the_mean_transmission_of_its_visibility():
    """Over many rays of length d through the banks, the transmission averages to
    exp(−β₀ d) within 2 % (rays much longer than the banks; the spread is small)."""
    preset = air_preset("fog-moderate", heterogeneity=0.5, heterogeneity_scale=10.0,
                        visibility=600.0)
    pair = plane_pair(48, 64, depth=400.0)
    record = sample_weather(pair, preset, 3, frame_rate=RATE)
    beta = record.atmosphere.extinction
    cams = [pose(rotation(yaw_deg=a, pitch_deg=b), (x, 0.0, z))
            for a, b, x, z in ((0, 0, 0, 0), (40, 5, 50, 10), (-70, -3, -30, 80),
                               (120, 2, 200, -40), (200, 0, -150, 300))]
    means = []
    for cam in cams:
        air = AirView(record.atmosphere, pair.intrinsics, cam, (48, 64), 0)
        d = air.distances(pair.depth1.double())
        v, u = torch.meshgrid(torch.arange(48.0, dtype=torch.float64),
                              torch.arange(64.0, dtype=torch.float64), indexing="ij")
        t = torch.exp(-air.optical_depth(u, v, d[0]))
        means.append((t / torch.exp(-beta * d[0])).mean())
        assert float(t.std()) > 0                               # the banks are there
    assert abs(float(torch.stack(means).mean()) - 1) < 0.02


def sequence_pairs(n_frames=3, height=24, width=32):
    """A forward-moving camera over a plane, as pairs (t, t + 1) of one scene."""
    cams = [pose(rotation(yaw_deg=1.0 * i), (0.2 * i, 0.0, 1.5 * i)) for i in range(n_frames)]
    g = torch.Generator().manual_seed(0)
    images = [0.2 + 0.6 * torch.rand(3, height, width, generator=g) for _ in cams]
    depths = [torch.full((1, height, width), 40.0 - 1.5 * i) for i in range(n_frames)]
    k = torch.tensor([[25.0, 0, (width - 1) / 2], [0, 25.0, (height - 1) / 2], [0, 0, 1]],
                     dtype=torch.float64)
    return [FramePair(id=PairId("demo", "training", "seq", i), image1=images[i],
                      image2=images[i + 1], depth1=depths[i], depth2=depths[i + 1],
                      intrinsics=k, cam2_from_cam1=cams[i + 1] @ torch.linalg.inv(cams[i]),
                      cam1_from_world=cams[i], cam2_from_world=cams[i + 1])
            for i in range(n_frames - 1)]


def test_density_field_is_the_same_in_frame_t_of_pairs_t_minus_1_and_t():
    a, b = sequence_pairs()
    preset = air_preset("fog-heavy", heterogeneity=0.6, heterogeneity_scale=8.0)
    rec_a = sample_weather(a, preset, 5, frame_rate=RATE, airlight=(0.8, 0.8, 0.8))
    rec_b = sample_weather(b, preset, 5, frame_rate=RATE, airlight=(0.8, 0.8, 0.8))
    assert torch.equal(rec_a.atmosphere.drift[1], rec_b.atmosphere.drift[0])
    assert float(rec_a.atmosphere.drift[1].norm()) > 0          # the wind moved it
    points = torch.rand(200, 3, dtype=torch.float64) * 60 - 30
    assert torch.equal(density_at(rec_a.atmosphere, points, 1),
                       density_at(rec_b.atmosphere, points, 0))
    assert not torch.equal(density_at(rec_a.atmosphere, points, 0),
                           density_at(rec_a.atmosphere, points, 1))
    # so frame t is the same image in both pairs
    out_a, out_b = render_pair(a, rec_a), render_pair(b, rec_b)
    assert torch.equal(out_a.image2, out_b.image1)
    assert torch.equal(out_a.opacity2, out_b.opacity1)
    assert float(out_b.opacity1.std()) > 0.005                  # heterogeneous


def test_right_view_reads_the_same_density_at_the_same_world_point():
    pair = plane_pair(24, 32, depth=30.0)
    preset = air_preset("fog-heavy", heterogeneity=0.6, heterogeneity_scale=8.0)
    record = sample_weather(pair, preset, 2, frame_rate=RATE, airlight=(0.8, 0.8, 0.8))
    right_from_left = torch.eye(4, dtype=torch.float64)
    right_from_left[0, 3] = -0.54
    left = View(pair.intrinsics, torch.eye(4, dtype=torch.float64), pair.depth1)
    right = stereo_view(left, right_from_left, pair.depth1.clone())
    airs = [AirView(record.atmosphere, v.intrinsics, v.cam_from_ref, (24, 32), 0)
            for v in (left, right)]
    # a world point on both rays: the ray integrals are those of the one world field
    v, u = torch.meshgrid(torch.arange(24.0, dtype=torch.float64),
                          torch.arange(32.0, dtype=torch.float64), indexing="ij")
    for air in airs:
        d = air.distances(pair.depth1.double())[0]
        fast = air.optical_depth(u, v, d)
        fine = reference_optical_depth(air, u, v, d, 512)
        assert float((torch.exp(-fast) - torch.exp(-fine)).abs().max()) < BOUND
    # the camera centres see the density of the world field at their own position
    centre = torch.tensor([[0.54, 0.0, 0.0]], dtype=torch.float64)
    field = density_at(record.atmosphere, centre, 0)
    tiny = airs[1].optical_depth(torch.tensor([15.5]), torch.tensor([11.5]),
                                 torch.tensor([1e-3], dtype=torch.float64))
    assert float(tiny / (record.atmosphere.extinction * 1e-3)) == pytest.approx(
        float(field), rel=0.02)
    # rendered: the right camera through the same record
    image, opacity = render_view(pair.image1, right, record, record.position, record.motion,
                                 _library(record))
    assert float(opacity.min()) > 0.5 and float(opacity.std()) > 0


def _library(record):
    from weathergen.engine import load_templates
    return load_templates(record.settings.templates)


@pytest.mark.parametrize("name, focal", [("fog-light", 400.0), ("fog-moderate", 400.0),
                                         ("fog-heavy", 1000.0), ("mist", 400.0),
                                         ("mist", 1000.0)])
def test_integration_error_is_below_its_bound_against_a_fine_reference(name, focal):
    """Coarse rays 6 and 8 pixels apart (focal lengths 400 and 1000), 128 geometric midpoint
    intervals per ray, against the midpoint rule with 1024 equal intervals along every pixel's
    own ray, with the strongest banks the bound is stated for (heterogeneity 0.8, 20 m)."""
    height, width = 60, 120
    k = torch.tensor([[focal, 0, 59.5], [0, focal, 29.5], [0, 0, 1]], dtype=torch.float64)
    rows = torch.linspace(3.0, 120.0, height, dtype=torch.float64)[:, None]
    depth = rows.expand(height, width).clone()
    depth[:10] = 1000.0                                          # sky
    depth[:, :30] = 6.0                                          # a near wall
    preset = load_preset(name, {"heterogeneity": "0.8", "heterogeneity_scale": "20"})
    pair = plane_pair(height, width)
    record = sample_weather(pair, preset, 4, frame_rate=RATE, airlight=(0.8, 0.8, 0.8))
    cam = pose(rotation(yaw_deg=20.0, pitch_deg=-4.0), (3.0, -1.5, 7.0))
    air = AirView(record.atmosphere, k, cam, (height, width), 1)
    v, u = torch.meshgrid(torch.arange(float(height), dtype=torch.float64),
                          torch.arange(float(width), dtype=torch.float64), indexing="ij")
    d = air.distances(depth[None])[0]
    fast = torch.exp(-air.optical_depth(u, v, d))
    fine = torch.exp(-reference_optical_depth(air, u, v, d, 1024))
    error = (fast - fine).abs()
    assert float(error.max()) < BOUND, float(error.max())
    assert float(error[10:].max()) < BOUND_SURFACES, float(error[10:].max())
    assert air.step == (6 if focal == 400 else 8)
    assert float((fine - torch.exp(-record.atmosphere.extinction * d)).abs().max()) > 0.01


def test_additive_particles_are_dimmed_by_the_air_in_front_of_them():
    """A drop at distance d_p adds t_p = exp(−β d_p) of its light to the fogged scene."""
    pair = plane_pair(40, 56, depth=20.0, dtype=torch.float64)
    preset = load_preset("rain-heavy", {"density": "2", "rain_rate": "0",
                                        "visibility": "10"})
    record = sample_weather(pair, preset, 1, frame_rate=RATE)
    assert record.count > 0
    clear = dataclasses.replace(record, atmosphere=None)
    light_clear = render_pair(pair, clear).image1 - pair.image1
    out = render_pair(pair, record)
    empty = record.select(torch.zeros(record.count, dtype=torch.bool))
    fogged = render_pair(pair, empty).image1
    light = out.image1 - fogged
    # each drop's light scaled by its own transmission: the ratio lies in the drops' range
    beta = record.atmosphere.extinction
    cam = pair.cam1_from_world
    dist = (record.position.double() @ cam[:3, :3].T + cam[:3, 3]).norm(dim=1)
    lo, hi = math.exp(-beta * float(dist.max()) * 1.2), math.exp(-beta * float(dist.min()) * 0.8)
    mask = light_clear > 1e-3
    ratio = light[mask] / light_clear[mask]
    assert float(ratio.min()) >= lo - 1e-9 and float(ratio.max()) <= hi + 1e-9
    assert float(ratio.max()) < 1


def test_combined_weather_composes_the_atmosphere_once():
    pair = plane_pair(24, 32, depth=50.0, dtype=torch.float64)
    combined = load_preset("rain-heavy+fog-moderate", {"fog-moderate.heterogeneity": "0",
                                                       "rain-heavy.density": "1"})
    layers = sample_weather(pair, combined, 0, frame_rate=RATE)
    assert isinstance(layers, LayeredParticles)
    beta = sum(r.atmosphere.extinction for r in layers.layers)
    empty = LayeredParticles(tuple(r.select(torch.zeros(r.count, dtype=torch.bool))
                                   for r in layers.layers), layers.names)
    out = render_pair(pair, empty)
    expected = 1 - torch.exp(-beta * distances(pair.depth1, pair.intrinsics))
    assert torch.allclose(out.opacity1[0], expected, rtol=0, atol=1e-14)
    # both layers' auto airlight is the pair's one estimate
    a, b = (r.atmosphere.airlight for r in layers.layers)
    assert torch.equal(a, b)


def test_record_with_an_atmosphere_round_trips_and_rerenders_the_same_bytes(tmp_path):
    pair = plane_pair(24, 32, depth=30.0)
    record = sample_weather(pair, load_preset("fog-moderate"), 9, frame_rate=RATE)
    path = record.save(tmp_path / "fog.npz")
    again = Particles.load(path)
    assert again.atmosphere.to_dict() == record.atmosphere.to_dict()
    assert torch.equal(render_pair(pair, again).image1, render_pair(pair, record).image1)
    # an explicit (e.g. attacked) density is stored as float16 and reloads to the same bytes
    dense = record.atmosphere.lattice(torch.float32) * 1.1
    attacked = record.replace(atmosphere=record.atmosphere.replace(density=dense)).quantized()
    again = Particles.load(attacked.save(tmp_path / "attacked.npz"))
    assert torch.equal(again.atmosphere.density, attacked.atmosphere.density)
    assert torch.equal(render_pair(pair, again).image1, render_pair(pair, attacked).image1)
    # records without an atmosphere store no entry for it
    snow = sample_weather(pair, load_preset("snow-light", {"snow_rate": "0"}), 0, frame_rate=RATE)
    assert snow.atmosphere is None
    assert "atmosphere" not in snow.to_numpy()


def test_gradcheck_of_the_density_and_the_airlight():
    pair = tilted_pair(12, 16)
    preset = air_preset("fog-heavy", heterogeneity=0.5, heterogeneity_scale=4.0)
    record = sample_weather(pair, preset, 0, frame_rate=RATE, airlight=(0.7, 0.75, 0.8))
    record = record.to(dtype=torch.float64)
    frame, c1, c2 = reference_transforms(pair)
    base = record.atmosphere.lattice(torch.float64).clone()

    def frames(density, airlight):
        atm = record.atmosphere.replace(density=density, airlight=airlight)
        out = render(pair.image1[None], pair.image2[None], pair.depth1[None], pair.depth2[None],
                     pair.intrinsics[None], c1[None], c2[None], record.replace(atmosphere=atm))
        return out.image1, out.image2, out.opacity1

    density = base.clone().requires_grad_()
    airlight = record.atmosphere.airlight.clone().requires_grad_()
    assert torch.autograd.gradcheck(frames, (density, airlight), fast_mode=True, atol=1e-7)
    image1, _, _ = frames(density, airlight)
    image1.sum().backward()
    assert float(density.grad.abs().sum()) > 0 and float(airlight.grad.abs().sum()) > 0


def test_preset_keys_of_the_atmosphere_are_validated():
    with pytest.raises(ConfigError, match="visibility"):
        load_preset("fog-light", {"visibility": "0.3"})             # kilometres typed as metres
    with pytest.raises(ConfigError, match="airlight"):
        load_preset("fog-light", {"airlight": "300,0,0"})
    with pytest.raises(ConfigError, match="heterogeneity"):
        load_preset("fog-light", {"heterogeneity": "1.5"})
    with pytest.raises(ConfigError, match="density"):
        load_preset("fog-light", {"visibility": "0"})              # nothing left to draw
    assert load_preset("fog-light", {"airlight": "[10, 20, 30]"}).airlight == (10, 20, 30)
    assert load_preset("fog-light", {"airlight": "auto"}).airlight == "auto"
    assert load_preset("fog-light").to_dict()["airlight"] == "auto"


def test_clear_presets_and_paper_presets_carry_no_atmosphere():
    pair = plane_pair(24, 32, depth=5.0)
    assert sample_weather(pair, load_preset("sparks-light"), 0, frame_rate=RATE).atmosphere \
        is None
    assert sample_weather(pair, load_preset("snow", {"count": "10"}), 0).atmosphere is None
    record = sample_field_particles(pair, load_preset("snow-light"), 0, frame_rate=RATE)
    assert record.atmosphere is not None and record.atmosphere.uniform


def test_particle_truth_sees_the_air_in_front_of_the_particles():
    from weathergen.engine import particle_truth

    pair = plane_pair(40, 56, depth=20.0, dtype=torch.float64)
    preset = load_preset("rain-heavy", {"density": "2", "rain_rate": "0", "visibility": "10"})
    record = sample_weather(pair, preset, 1, frame_rate=RATE)
    with_air = particle_truth(pair, record)
    without = particle_truth(pair, dataclasses.replace(record, atmosphere=None))
    covered = without.weight > 1e-4
    assert bool(covered.any())
    ratio = with_air.weight[covered] / without.weight[covered]
    assert float(ratio.max()) < 1 and float(ratio.min()) > 0
    assert float(with_air.opacity.sum()) < float(without.opacity.sum())
    # combined weather: the same through the layered path
    combined = load_preset("rain-heavy+fog-heavy", {"rain-heavy.density": "2",
                                                    "rain-heavy.rain_rate": "0"})
    layers = sample_weather(pair, combined, 1, frame_rate=RATE)
    clear = LayeredParticles(tuple(dataclasses.replace(r, atmosphere=None)
                                   for r in layers.layers), layers.names)
    assert float(particle_truth(pair, layers).weight.sum()) < \
        float(particle_truth(pair, clear).weight.sum())


def test_uniform_atmospheres_beside_a_heterogeneous_one_read_no_ray_tables(monkeypatch):
    """A view with heterogeneous fog and a uniform veil (snow's) reads the coarse rays' tables
    for the fog alone, and its transmission is the same to the bit as when the veil's slot reads
    them too (where τ = β₀ L exactly)."""
    from weathergen.engine.rendering.transmittance import Air
    from weathergen.engine.weather.atmosphere import Atmosphere

    drift = torch.zeros(2, 3, dtype=torch.float64)
    fog = Atmosphere(extinction=0.02, airlight=torch.tensor([0.8, 0.8, 0.9]), drift=drift,
                     heterogeneity=0.5, seed=3)
    veil = Atmosphere(extinction=0.005, airlight=torch.tensor([0.9, 0.9, 0.9]), drift=drift)
    k = torch.tensor([[30.0, 0, 20], [0, 30.0, 15], [0, 0, 1]], dtype=torch.float64)
    depth = torch.linspace(2.0, 80.0, 30 * 40, dtype=torch.float64).view(1, 1, 30, 40)

    def pixels(slot_hetero):
        air = Air([[fog, veil], [veil, fog]], k.expand(2, 3, 3), torch.eye(4).expand(2, 4, 4)
                  .double(), (30, 40), [0, 1])
        if slot_hetero is not None:
            air.slot_hetero = slot_hetero
        calls = []
        lookup = Air._lookup
        monkeypatch.setattr(Air, "_lookup", lambda self, *a: calls.append(1) or lookup(self, *a))
        t, airlight = air.pixels(depth.expand(2, 1, 30, 40), torch.float64)
        monkeypatch.setattr(Air, "_lookup", lookup)
        return t, airlight, len(calls)

    # the fog sits in slot 0 of view 0 and slot 1 of view 1: both slots read the tables
    t, a, calls = pixels(None)
    assert calls == 2
    same_t, same_a, _ = pixels([True, True])
    assert torch.equal(t, same_t) and torch.equal(a, same_a)
    # one view with the fog in slot 0 alone: slot 1 (the veil) reads nothing
    air = Air([[fog, veil]], k[None], torch.eye(4, dtype=torch.float64)[None], (30, 40), [0])
    assert air.slot_hetero == [True, False]
    calls = []
    lookup = Air._lookup
    monkeypatch.setattr(Air, "_lookup", lambda self, *a: calls.append(1) or lookup(self, *a))
    t1, a1 = air.pixels(depth, torch.float64)
    assert len(calls) == 1
    air.slot_hetero = [True, True]
    t2, a2 = air.pixels(depth, torch.float64)
    assert len(calls) == 3 and torch.equal(t1, t2) and torch.equal(a1, a2)
    # and the veil's slot is Koschmieder's τ = β₀ L on top of the fog's
    fog_only = Air([[fog]], k[None], torch.eye(4, dtype=torch.float64)[None], (30, 40), [0])
    t_fog, _ = fog_only.pixels(depth, torch.float64)
    length = distances(depth[0], k)[None].clamp(max=veil.sky_distance)
    assert torch.allclose(t1, t_fog * torch.exp(-veil.extinction * length), rtol=1e-12, atol=0)
