"""Looks measured against their reference: streaks continuous (blur samples at most a pixel
apart, up to the cap), far particles the size and light the projection gives (the pixel integral
of the footprint's disc at the particle's exact centre), sparks as bright as the paper's research
code draws them on the same scene."""

from __future__ import annotations

import pytest
import torch

from engine_scenes import wall_scene
from weathergen.datasets import frame_rate_of
from weathergen.engine import load_preset, sample_field_particles, sample_particles
from weathergen.engine.renderer import reference_transforms
from weathergen.engine.tracks import (MAX_BLUR_SAMPLES, Views, blur_samples, pair_tracks,
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
