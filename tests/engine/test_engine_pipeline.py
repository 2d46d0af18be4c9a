"""One call for every weather: ``Weather(preset, seed).render(pair)`` for each kind of preset,
the README's library example run with one preset of each kind, and the lower-level samplers'
one-line refusals of a preset of the wrong kind."""

from __future__ import annotations

import re

import pytest
import torch

from conftest import PROJECT_ROOT
from test_docs_examples import python_blocks
from weathergen.datasets import demo_pairs
from weathergen.engine import (Weather, load_particles, load_preset, render_pair, sample_field_particles,
                               sample_layers, sample_particles, sample_weather)
from weathergen.errors import ConfigError

#: One preset of each kind: the paper's, a weather field, an atmosphere alone, a combination.
KINDS = {"paper": "snow", "field": "snow-moderate", "atmosphere": "fog-moderate",
         "combined": "rain-heavy+fog-light"}


@pytest.fixture(scope="module")
def pair():
    return demo_pairs(scenes=["street"], frames_per_scene=2)[0]


def _library_block() -> str:
    readme = (PROJECT_ROOT / "README.md").read_text()
    blocks = [code for _, code in python_blocks(readme) if "Weather(" in code]
    assert len(blocks) == 1, "the README has one library example built on Weather"
    return blocks[0]


@pytest.mark.parametrize("kind", KINDS)
def test_the_readme_library_example_runs_with_every_kind_of_preset(kind, tmp_path, monkeypatch):
    code, count = re.subn(r'Weather\("snow"', f'Weather("{KINDS[kind]}"', _library_block())
    assert count == 1
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    out, pair = namespace["out"], namespace["pair"]
    assert out.image1.shape == (1, 3, *pair.size)
    # the weather shows: some pixel of frame 1 changed
    assert (out.image1[0] - pair.image1).abs().amax() > 1 / 255
    again = load_particles(tmp_path / "pair.npz")
    assert torch.equal(render_pair(pair, again).image1, out.image1)


def test_the_frame_rate_comes_from_the_pair(pair):
    assert pair.frame_rate == 24.0                  # the demo reader's
    preset = load_preset("snow-moderate")
    one = Weather(preset, seed=3).sample(pair)
    assert torch.equal(one.position, sample_weather(pair, preset, 3, frame_rate=24.0).position)
    other = sample_weather(pair, preset, 3, frame_rate=12.0)   # an explicit rate still wins
    assert not torch.equal(one.offset1, other.offset1)
    pair_without = type(pair)(**{**pair.__dict__, "frame_rate": None})
    with pytest.raises(ConfigError, match="frame rate"):
        Weather(preset, seed=3).sample(pair_without)


def test_overrides_apply_to_a_named_preset(pair):
    few = Weather("snow", seed=0, overrides={"count": "20"}).sample(pair)
    assert 0 < len(few) <= 20


@pytest.mark.parametrize("call, name, wants", [
    (sample_particles, "fog-moderate", "sample_particles"),
    (sample_particles, "snow-moderate", "sample_particles"),
    (sample_particles, "rain-heavy+fog-light", "sample_particles"),
    (sample_field_particles, "snow", "sample_field_particles"),
    (sample_layers, "snow-moderate", "sample_layers"),
])
def test_a_preset_of_the_wrong_kind_is_refused_in_one_line(pair, call, name, wants):
    with pytest.raises(ConfigError) as info:
        call(pair, load_preset(name), 0)
    message = str(info.value)
    assert "\n" not in message and wants in message and "sample_weather" in message
    assert "Weather(" in message
