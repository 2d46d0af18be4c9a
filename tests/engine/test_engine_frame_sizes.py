"""The paper's presets on any frame size: counts scaled by area, sizes kept in pixels (or scaled by
the diagonal on request), explicit values kept, the 1024x436 frame unchanged."""

from __future__ import annotations

import math

import pytest
import torch

from engine_scenes import plane_pair
from weathergen.engine import frame_scaling, load_preset, sample_particles
from weathergen.engine.weather.presets import (FieldPreset, FrameScaling, field_preset_keys,
                                               scaled_count, scaled_size)
from weathergen.errors import ConfigError

SINTEL, DEMO, KITTI = (436, 1024), (176, 384), (375, 1242)
FIELDS = ("position", "motion", "offset1", "offset2", "color", "transparency", "template",
          "rotation", "scale", "defocus")


# By hand: 3000 x 384 x 176 / (1024 x 436) = 454.13 -> 454; 3000 x 1242 x 375 / (1024 x 436) =
# 3129.6 -> 3130; fog's 60 -> 9.08 -> 9 and 62.6 -> 63; sizes stay the paper's pixels.
@pytest.mark.parametrize("name, frame, count", [
    ("snow", SINTEL, 3000), ("snow", DEMO, 454), ("snow", KITTI, 3130),
    ("fog", SINTEL, 60), ("fog", DEMO, 9), ("fog", KITTI, 63)])
def test_counts_on_three_frame_sizes(name, frame, count):
    preset = load_preset(name)
    scaling = frame_scaling(preset, *frame)
    assert (scaling.count, scaling.size, scaling.pixel_scale) == (count, preset.size, 1.0)
    assert (scaling.count_rule, scaling.size_rule) == ("area", "fixed")
    assert scaling.count == round(preset.count * frame[0] * frame[1] / (1024 * 436))


@pytest.mark.parametrize("frame, count", [(SINTEL, 3000), (DEMO, 454), (KITTI, 3130)])
def test_sampling_places_the_frames_count(frame, count):
    pair = plane_pair(*frame, depth=3.5)
    assert sample_particles(pair, load_preset("snow"), seed=1).count == count


@pytest.mark.parametrize("name", ["snow", "rain", "sparks", "fog"])
def test_a_sintel_size_frame_is_bit_identical_to_unscaled_sampling(name):
    """On 1024x436 every rule gives the preset's own count, size and radii: the same bytes as a
    preset that scales nothing (what sampling did before frame sizes were taken into account)."""
    pair = plane_pair(*SINTEL, depth=2.5, near_block=True)
    unscaled = sample_particles(pair, load_preset(name, {"scale_count": False}), seed=3)
    assert unscaled.count == load_preset(name).count
    for overrides in ({}, {"scale_size": True}):
        parts = sample_particles(pair, load_preset(name, overrides), seed=3)
        for field in FIELDS:
            assert torch.equal(getattr(parts, field), getattr(unscaled, field)), (name, field)


def test_explicit_counts_and_sizes_are_kept():
    snow = load_preset("snow", {"count": "500"})
    assert (snow.scale_count, snow.scale_size) == (False, False)
    for frame in (SINTEL, DEMO, KITTI):
        assert frame_scaling(snow, *frame).count == 500
        assert frame_scaling(snow, *frame).count_rule == "fixed"
    assert sample_particles(plane_pair(*DEMO, depth=3.5), snow, seed=0).count == 500
    assert frame_scaling(load_preset("snow", {"count": 500}), *KITTI).count == 500  # not a string
    # the switch set with the count: 500 per 1024x436 frame, 500 x 0.15138 = 75.7 on the demo
    per_sintel = load_preset("snow", {"count": "500", "scale_count": "true"})
    assert frame_scaling(per_sintel, *DEMO).count == 76


def test_a_preset_file_count_is_per_sintel_frame_unless_it_says_otherwise(tmp_path):
    plain = tmp_path / "mine.toml"
    plain.write_text("count = 500\n")
    assert frame_scaling(load_preset(plain), *DEMO).count == 76
    fixed = tmp_path / "fixed.toml"
    fixed.write_text("count = 500\nscale_count = false\n")
    assert frame_scaling(load_preset(fixed), *DEMO).count == 500
    # an explicit size stays as given even where the preset file scales sizes
    resized = tmp_path / "resized.toml"
    resized.write_text("scale_size = true\n")
    assert frame_scaling(load_preset(resized), *DEMO).size == 27
    sized = load_preset(resized, {"size": "31"})
    assert frame_scaling(sized, *DEMO).size == 31 and not sized.scale_size


# Diagonal ratios: demo sqrt(384^2 + 176^2) / sqrt(1024^2 + 436^2) = 0.37953, KITTI 1.16572.
# snow 71 -> 26.95 -> 27 and 82.77 -> 83; rain 51 -> 19.36 -> 19 and 59.45 -> 59; fog 451 ->
# 171.2 -> 171 and 525.7 -> 525 (the nearest odd number).
@pytest.mark.parametrize("name, frame, size", [
    ("snow", SINTEL, 71), ("snow", DEMO, 27), ("snow", KITTI, 83),
    ("rain", DEMO, 19), ("rain", KITTI, 59), ("fog", DEMO, 171), ("fog", KITTI, 525)])
def test_sizes_scale_with_the_diagonal_on_request(name, frame, size):
    preset = load_preset(name, {"scale_size": True})
    scaling = frame_scaling(preset, *frame)
    assert scaling.size == size and scaling.size % 2 == 1 and scaling.size_rule == "diagonal"
    assert scaling.pixel_scale == pytest.approx(math.hypot(*frame) / math.hypot(436, 1024), rel=1e-12)
    resized = load_preset(name, {"scale_size": True, "scale_count": False})
    assert frame_scaling(resized, *frame).count == preset.count


def test_rounding_is_exact_and_deterministic():
    # 3 x 218 x 1024 / (1024 x 436) = 1.5 exactly: halves go up
    assert scaled_count(3, 218, 1024) == 2
    assert scaled_count(1, 8, 8) == 1          # a preset that asks for weather gets a particle
    assert scaled_count(0, 2000, 2000) == 0
    assert scaled_count(1_000_000, 436, 1024) == 1_000_000
    # a 872x2048 frame has twice Sintel's diagonal: 2 x 1 = 2 is a tie between 1 and 3 (above)
    assert scaled_size(1, 872, 2048) == 3 and scaled_size(71, 872, 2048) == 143
    assert scaled_size(451, 4360, 10240) == 2047        # at most the schema's largest size
    for size in range(1, 2048, 2):
        assert scaled_size(size, *SINTEL) == size and scaled_size(size, 1024, 436) == size
        for frame in (DEMO, KITTI, (1080, 1920), (7, 9)):
            x = size * math.hypot(*frame) / math.hypot(436, 1024)
            got = scaled_size(size, *frame)
            assert got % 2 == 1 and (abs(got - x) <= 1 + 1e-9 or got == 2047), (size, frame)
    with pytest.raises(ConfigError, match="0x176"):
        frame_scaling(load_preset("snow"), 176, 0)


def test_scaling_record_round_trip():
    scaling = frame_scaling(load_preset("sparks", {"scale_size": True}), *KITTI)
    data = scaling.to_dict()
    assert data["reference"] == [436, 1024]
    assert FrameScaling.from_dict(data) == scaling
    assert "3130 particles = 3000 x area 1242x375 / 1024x436" in scaling.describe()


def test_field_presets_stay_in_world_units():
    keys = {f.name for f in field_preset_keys()}
    assert not keys & {"count", "size", "scale_count", "scale_size"}
    with pytest.raises(ConfigError, match="unknown key 'scale_count'"):
        load_preset("snow-light", {"scale_count": "false"})
    assert isinstance(load_preset("snow-light"), FieldPreset)
