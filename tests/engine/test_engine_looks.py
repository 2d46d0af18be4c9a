"""Looks measured against their reference: streaks continuous (blur samples at most a pixel
apart, up to the cap), far particles the size and light the projection gives (the pixel integral
of the footprint's disc at the particle's exact centre), sparks as bright as the paper's research
code draws them on the same scene."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import torch.nn.functional as F

from engine_scenes import plane_pair, wall_scene
from weathergen.datasets import frame_rate_of
from weathergen.engine import (BETA_ATTACK, Particles, RenderSettings, load_preset,
                               load_templates, render_pair, sample_field_particles,
                               sample_particles)
from weathergen.engine.rendering.renderer import reference_transforms
from weathergen.engine.rendering.tracks import (MAX_BLUR_SAMPLES, Views, blur_samples, pair_tracks,
                                                streak_samples)


def tracks_of(pair, record):
    """The core's tracks of one record drawn into a pair (views: frame 1, frame 2)."""
    _, c1, c2 = reference_transforms(pair)
    views = Views.of(torch.stack((pair.intrinsics, pair.intrinsics)), torch.stack((c1, c2)),
                     torch.stack((pair.depth1, pair.depth2)))
    return pair_tracks([record], views, 80, beta=30.0, dtype=torch.float64)[1]


def gaps_per_track(tracks):
    """Per track: the largest pixel distance between consecutive blur samples, the streak's
    drawn length (the sum of those distances), its depth range (far / near), its sample count,
    for tracks whose samples all lie in front of the camera inside a generous image margin."""
    inst = blur_samples(tracks, torch.float64)
    samples, _ = streak_samples(tracks)
    track = torch.repeat_interleave(torch.arange(tracks.count), samples)
    gap = torch.hypot(inst.u[1:] - inst.u[:-1], inst.v[1:] - inst.v[:-1])
    same = track[1:] == track[:-1]
    t = track[1:][same]
    largest = torch.zeros(tracks.count, dtype=torch.float64).scatter_reduce(
        0, t, gap[same], "amax")
    length = torch.zeros(tracks.count, dtype=torch.float64).index_add_(0, t, gap[same])
    z_min = torch.full((tracks.count,), float("inf"), dtype=torch.float64).scatter_reduce(
        0, track, inst.z, "amin")
    z_max = torch.zeros(tracks.count, dtype=torch.float64).scatter_reduce(
        0, track, inst.z, "amax")
    inside = torch.ones(tracks.count, dtype=torch.bool).scatter_reduce(
        0, track, (inst.z > 0.05) & (inst.u.abs() < 3000) & (inst.v.abs() < 3000), "amin")
    return largest, length, z_max / z_min, samples, inside


def assert_continuous(tracks):
    largest, length, depth_ratio, samples, inside = gaps_per_track(tracks)
    blurred = (tracks.samples > 1) & inside
    capped = blurred & (samples == MAX_BLUR_SAMPLES)
    free = blurred & ~capped
    assert int(free.sum()) > 100
    assert float(largest[free].max()) <= 1.0 + 1e-9
    # beyond the cap: gaps of at most the streak's length (at its nearer end's scale) / (K − 1)
    bound = length * depth_ratio / (MAX_BLUR_SAMPLES - 1)
    assert bool((largest[capped] <= bound[capped] * (1 + 1e-9)).all())
    assert int(capped.sum()) <= 0.1 * int(blurred.sum())
    return samples


@pytest.mark.parametrize("frame", [0, 1], ids=["frame1", "frame2"])
def test_paper_rain_under_forward_motion_draws_continuous_streaks(frame):
    """Paper rain at KITTI's forward step (0.77 units): 20 samples along 0.15 (X2 − X1) left
    gaps of 3 px (p90, frame 2) before; now every streak's samples lie at most a pixel apart
    (or the streak's length / 255 beyond the cap), in both frames."""
    pair = wall_scene(forward=0.77)
    tracks = tracks_of(pair, sample_particles(pair, load_preset("rain"), seed=0))
    half = tracks.count // 2
    rows = torch.arange(frame * half, (frame + 1) * half)
    one = type(tracks)(**{k: getattr(tracks, k)[rows] for k in tracks.__dataclass_fields__})
    samples = assert_continuous(one)
    assert int(samples.max()) > 20                     # long streaks did get more samples


@pytest.mark.parametrize("forward", [0.0, 0.77])
def test_field_rain_draws_continuous_streaks(forward):
    pair = wall_scene(forward=forward)
    record = sample_field_particles(pair, load_preset("rain-moderate", {"density": 20}), seed=0,
                                    frame_rate=frame_rate_of(pair.id.dataset))
    assert_continuous(tracks_of(pair, record))


def test_short_streaks_keep_the_presets_samples_bit_for_bit():
    """A streak shorter than K − 1 pixels keeps the preset's K samples and spacing (so the
    paper's look at its own sample count is unchanged); θ / K_t keeps every track's total θ."""
    pair = wall_scene()
    tracks = tracks_of(pair, sample_particles(pair, load_preset("sparks"), seed=0))
    largest, length, depth_ratio, samples, inside = gaps_per_track(tracks)
    short = length * depth_ratio < (tracks.samples - 1) * 0.999
    assert int(short.sum()) > 100
    got_samples, got_spacing = streak_samples(tracks)
    assert torch.equal(got_samples[short], tracks.samples[short])
    assert torch.equal(got_spacing[short], tracks.spacing[short])
    inst = blur_samples(tracks, torch.float64)
    total = torch.zeros(tracks.count, dtype=torch.float64).index_add_(
        0, torch.repeat_interleave(torch.arange(tracks.count), got_samples), inst.theta)
    torch.testing.assert_close(total, tracks.theta, rtol=1e-12, atol=0)


@pytest.mark.parametrize("name, grey", [("rain", 1.5), ("sparks", 4.0)])
def test_softened_stamps_wider_sample_gaps_leave_the_frames_within_a_few_grey_levels(
        monkeypatch, name, grey):
    """Softened stamps (defocused glows) take blur samples (b − 1) / 2 px apart: a quarter
    fewer patch pixels to splat, and the frames within ``grey`` levels (of 255) of the one-pixel
    rule's everywhere."""
    import weathergen.engine.rendering.renderer as renderer_module
    from weathergen.engine.rendering import stamps as stamps_module

    pair = wall_scene()
    record = sample_particles(pair, load_preset(name), seed=0)
    build = stamps_module.build
    drawn = {}

    def counting_splat(inst, stamps, depth, **options):
        drawn[len(drawn)] = int(((stamps.side.index_select(0, inst.entry) + 1) ** 2).sum())
        return splat(inst, stamps, depth, **options)

    splat = renderer_module.splat
    monkeypatch.setattr(renderer_module, "splat", counting_splat)
    with torch.no_grad():
        spaced = render_pair(pair, record)

        def one_pixel_build(*args, **kwargs):
            stamps = build(*args, **kwargs)
            assert bool((stamps.gap > 1).any())
            return dataclasses.replace(stamps, gap=torch.ones_like(stamps.gap))

        monkeypatch.setattr(renderer_module, "build", one_pixel_build)
        dense = render_pair(pair, record)
    assert drawn[0] < 0.75 * drawn[1]
    for a, b in ((spaced.image1, dense.image1), (spaced.image2, dense.image2)):
        difference = 255 * (a - b).abs()
        assert 0 < float(difference.max()) <= grey
        assert float(difference.mean()) < 0.1


# -- far particles: the projection's size and light ------------------------------------------

CELL = 24


def far_particles(name: str, depth: float, count: int, seed: int, size=(192, 480)):
    """``count`` particles of a paper preset at one depth, one per 24-px cell of a black frame,
    at random sub-pixel positions, templates and rotations; white, θ = 1, additive, no blur.
    Returns the pair, the record and the particles' exact pixel positions (u, v)."""
    preset = load_preset(name, {"motion_blur": "false", "blend": "additive"})
    lib = load_templates(preset.templates)
    height, width = size
    pair = plane_pair(height, width, depth=50.0, world=False, dtype=torch.float64)
    pair.image1.zero_()
    pair.image2.zero_()
    g = torch.Generator().manual_seed(seed)
    cols = width // CELL
    cell = torch.arange(count)
    u = (cell % cols) * CELL + CELL / 2 + torch.rand(count, generator=g, dtype=torch.float64)
    v = (cell // cols) * CELL + CELL / 2 + torch.rand(count, generator=g, dtype=torch.float64)
    assert int(cell.max()) // cols * CELL + CELL <= height
    d = torch.full((count,), depth, dtype=torch.float64)
    k = pair.intrinsics
    position = torch.stack(((u - k[0, 2]) * d / k[0, 0], (v - k[1, 2]) * d / k[1, 1], d), 1)
    footprint = preset.size * min(1.0, 1.0 / (depth * preset.depth_decay))
    zero = torch.zeros(count, 3, dtype=torch.float64)
    record = Particles(position=position, motion=zero, offset1=zero, offset2=zero,
                       color=torch.ones(count, 3, dtype=torch.float64),
                       transparency=torch.ones(count, dtype=torch.float64),
                       template=torch.randint(0, lib.count, (count,), generator=g),
                       rotation=torch.rand(count, generator=g, dtype=torch.float64) * 2 * math.pi,
                       scale=torch.full((count,), max(footprint, 1.0) / lib.resolution,
                                        dtype=torch.float64),
                       defocus=torch.zeros(count, dtype=torch.int64), frame="camera1",
                       settings=RenderSettings.from_preset(preset, lib))
    return pair, record, u, v


def ideal(record, u, v, shape, sub: int = 16) -> torch.Tensor:
    """The projection's ideal: each particle's template (full resolution), rotated, as a disc of
    the footprint's diameter centred exactly at (u, v), integrated over every pixel with
    ``sub x sub`` samples. Shape: -> (H, W)."""
    lib = load_templates(record.settings.templates)
    image = torch.zeros(shape, dtype=torch.float64)
    footprint = float(record.scale[0]) * lib.resolution
    half = int(footprint / 2) + 2
    steps = (torch.arange(sub, dtype=torch.float64) + 0.5) / sub - 0.5
    offsets = (torch.arange(-half, half + 1, dtype=torch.float64)[:, None] + steps).reshape(-1)
    side = 2 * half + 1
    for i in range(record.count):
        cu, cv = round(float(u[i])), round(float(v[i]))
        gy, gx = torch.meshgrid(cv + offsets - v[i], cu + offsets - u[i], indexing="ij")
        c, s = math.cos(float(record.rotation[i])), math.sin(float(record.rotation[i]))
        xn, yn = (c * gx + s * gy) / (footprint / 2), (-s * gx + c * gy) / (footprint / 2)
        alpha = lib.alphas[int(record.template[i])][None, None].double()
        value = F.grid_sample(alpha, torch.stack((xn, yn), -1)[None], mode="bilinear",
                              align_corners=False)[0, 0] * ((xn * xn + yn * yn) <= 1)
        image[cv - half:cv + half + 1, cu - half:cu + half + 1] += \
            value.view(side, sub, side, sub).mean((1, 3))
    return image


def per_particle(image: torch.Tensor, u, v):
    """Each cell's light (sum), r.m.s. radius about the particle's exact centre and peak.
    Shape: -> (3, n)."""
    cols = image.shape[1] // CELL
    ys, xs = torch.meshgrid(torch.arange(CELL, dtype=torch.float64),
                            torch.arange(CELL, dtype=torch.float64), indexing="ij")
    out = []
    for i in range(len(u)):
        r, c = i // cols, i % cols
        p = image[r * CELL:(r + 1) * CELL, c * CELL:(c + 1) * CELL]
        light = p.sum()
        spread = (p * ((xs - (u[i] - c * CELL)) ** 2 + (ys - (v[i] - r * CELL)) ** 2)).sum()
        out.append(torch.stack((light, torch.sqrt(spread / light), p.max())))
    return torch.stack(out, 1)


@pytest.mark.parametrize("name", ["snow", "sparks"])
@pytest.mark.parametrize("depth", [2.0, 2.5, 3.0])
def test_far_particles_have_the_projections_size_and_light(name, depth):
    """Far particles (2–3 units: 1.5–4 px footprints) against the pixel integral of their
    footprint's disc at the exact centre: median light within 3 %, median r.m.s. radius within
    5 %, median peak within 10 %. A pixel-centred stamp shifted by a bilinear tent (the splat
    before phase stamps) was 9–34 % too wide and its peaks 8–26 % too low here."""
    pair, record, u, v = far_particles(name, depth, 120, seed=int(10 * depth))
    got = per_particle(render_pair(pair, record).image1[0, 0], u, v).median(1).values
    want = per_particle(ideal(record, u, v, pair.image1.shape[-2:]), u, v).median(1).values
    light, rms, peak = (got / want).tolist()
    assert abs(light - 1) <= 0.03, (light, got, want)
    assert abs(rms - 1) <= 0.05, (rms, got, want)
    assert abs(peak - 1) <= 0.10, (peak, got, want)


def test_far_particles_are_differentiable_in_their_position():
    """Phase stamps move with the particle: float64 gradcheck of the frames with respect to the
    offsets of a few far snowflakes and sparks (footprints of 1.5–4 px, phases of 1 / 4 and
    1 / 2 pixel)."""
    g = torch.Generator().manual_seed(2)
    weights = torch.rand(2, 2 * 3 * 24 * 48, generator=g, dtype=torch.float64)
    for name, depth in (("snow", 2.2), ("sparks", 2.6), ("snow", 1.3)):
        pair, record, _, _ = far_particles(name, depth, 2, seed=3, size=(24, 48))
        lib = load_templates(record.settings.templates)

        def frames(offset1, offset2, pair=pair, record=record, lib=lib):
            out = render_pair(pair, record.replace(offset1=offset1, offset2=offset2), lib,
                              beta=BETA_ATTACK)
            return weights @ torch.cat((out.image1.reshape(-1), out.image2.reshape(-1)))

        leaves = [(0.01 * torch.randn(2, 3, generator=g, dtype=torch.float64))
                  .requires_grad_(True) for _ in range(2)]
        assert torch.autograd.gradcheck(frames, leaves, eps=1e-7, atol=1e-5, rtol=1e-4)


def test_sparks_are_as_bright_as_the_research_codes():
    """Sparks (the paper's table colour 191, 79, 64) on the wall scene: mean 8-bit change of
    frame 1 over three seeds within 15 % of the research code's 3.01 on the same scene and
    count (two seeds, measured outside this repository)."""
    pair = wall_scene()
    clean = torch.round(pair.image1 * 255)
    change = [float((torch.round(render_pair(pair, sample_particles(pair, load_preset("sparks"),
                                                                    seed=seed)).image1[0] * 255)
                     - clean).abs().mean()) for seed in range(3)]
    assert abs(sum(change) / 3 / 3.01 - 1) <= 0.15, change
