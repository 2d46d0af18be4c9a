"""Combined presets above the engine: each layer's seed in a run, what `presets` and `inspect` show,
and the one-line refusal of the commands that cannot draw them yet."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from engine_scenes import plane_pair
from weathergen.cli.main import _register, cli
from weathergen.engine import (EXAMPLE_COMBINATIONS, LayeredParticles, layer_seed, load_preset,
                               sample_layers, scene_seed)
from weathergen.errors import ConfigError
from weathergen.framepair import PairId
from weathergen.render.particles import layer_seeds, pair_particles, pair_seed, weather_seed


def run(*args):
    _register()
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_line_error(res) -> str:
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), res.output
    return lines[0]


def test_each_layer_seed_comes_from_its_own_models_seed():
    c = load_preset("snow+fog-light")
    first, second = PairId("sintel", "training", "alley_1", 1), PairId("sintel", "training", "alley_1", 2)
    s1, s2 = layer_seeds(c, 7, first), layer_seeds(c, 7, second)
    # the paper layer: from the pair's own seed, another for every pair
    assert s1[0] == layer_seed(pair_seed(7, first), "snow") and s1[0] != s2[0]
    # the field layer: from the scene's field seed, one field for the whole scene
    assert s1[1] == s2[1] == layer_seed(scene_seed(7, "sintel", "training", "alley_1"), "fog-light")
    assert layer_seeds(c, 8, first) != s1
    assert weather_seed(c, 7, first) == pair_seed(7, first)


def test_a_runs_pair_samples_every_layer_with_its_seed():
    pair = plane_pair(40, 56)
    c = load_preset("snow+fog-light", {"snow.count": "100"})
    layers = pair_particles(pair, c, 3, frame_rate=30.0)
    assert isinstance(layers, LayeredParticles)
    expected = sample_layers(pair, c, layer_seeds(c, 3, pair.id), frame_rate=30.0)
    for a, b in zip(layers.layers, expected.layers):
        assert torch.equal(a.position, b.position) and a.settings == b.settings


@pytest.mark.parametrize("command", ["render", "attack"])
def test_render_and_attack_refuse_a_combination_in_one_line(tmp_path, command):
    out = tmp_path / "out"
    line = one_line_error(run(command, "--preset", "rain-heavy+fog-light", "--out", out))
    assert line == ("Error: --preset rain-heavy+fog-light: combined presets (layers joined by +) "
                    "are not yet supported by render and attack; `weathergen presets "
                    "rain-heavy+fog-light` shows how they resolve")
    assert not out.exists()
    # a bad combination is named as such first
    line = one_line_error(run(command, "--preset", "snow+", "--out", out))
    assert "--preset snow+: layer 2 of 2 is empty" in line and not out.exists()
    line = one_line_error(run(command, "--preset", "snow+fog-light", "--set", "density=3", "--out", out))
    assert "--set density: not a key of layer 1 (snow, a paper preset)" in line


def test_weather_augment_refuses_a_combination():
    from weathergen.training import WeatherAugment

    for given in ("snow+fog", load_preset("snow+fog")):
        with pytest.raises(ConfigError, match="not yet supported by WeatherAugment"):
            WeatherAugment(given)


def test_presets_lists_example_combinations_and_shows_each_layer():
    res = run("presets")
    assert res.exit_code == 0, res.output
    for name in EXAMPLE_COMBINATIONS:
        assert f" {name} " in res.output, name
    assert "rain-heavy (field) + fog-light (field)" in res.output
    res = run("presets", "snow+fog-light", "--set", "snow.count=77", "--set", "2.density=0.07")
    assert res.exit_code == 0, res.output
    assert "layer 1 of snow+fog-light: preset snow (paper model)" in res.output
    assert "layer 2 of snow+fog-light: preset fog-light (field model)" in res.output
    assert " 77 " in res.output and " 0.07 " in res.output
    line = one_line_error(run("presets", "snow+snow"))
    assert "layer 'snow' is given twice" in line


def test_inspect_shows_the_layers_of_a_metadata_file(tmp_path):
    from weathergen.outputs.metadata import pair_metadata, write_metadata

    pair = plane_pair(40, 56)
    c = load_preset("snow+fog", {"snow.count": "50", "fog.count": "3"})
    layers = sample_layers(pair, c, (1, 2), frame_rate=30.0)
    arrays = pair_metadata(layers, pair.id, 5, c.to_dict(), c.name, layer_seeds=(1, 2))
    arrays["files"] = np.array(json.dumps([]))
    path = write_metadata(tmp_path / "frame_0001.npz", arrays)
    res = run("inspect", path)
    assert res.exit_code == 0, res.output
    assert "snow+fog" in res.output and "(v4)" in res.output
    assert "snow: 50 particles" in res.output and "fog: 3 particles" in res.output
    assert "per-particle values of layer snow" in res.output
    assert "per-particle values of layer fog" in res.output
