"""Combined presets (``rain-heavy+fog-light``): loading, overrides per layer, bad combinations,
severity ladders in combination, sampling with a seed per layer, and the layered particle file."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from engine_scenes import plane_pair
from weathergen.datasets import frame_rate_of
from weathergen.engine import (EXAMPLE_COMBINATIONS, CombinedPreset, FieldPreset, LayeredParticles,
                               Particles, Preset, layer_seed, load_particles, load_preset,
                               sample_layers, sample_weather)
from weathergen.engine.records.particles import TENSOR_FIELDS
from weathergen.errors import ConfigError, FormatError


def spelled(exc: pytest.ExceptionInfo) -> str:
    """The message as the command line prints it (parameters spelled as options)."""
    from weathergen.cli.options import option_of

    return exc.value.render(option_of)


#: The frame rate of the test pairs' data (a dataset without a recorded rate).
RATE = frame_rate_of("synthetic")


@pytest.fixture(scope="module")
def pair():
    return plane_pair(48, 64, depth=4.0)


def same_record(a: Particles, b: Particles) -> bool:
    return (all(torch.equal(getattr(a, n), getattr(b, n)) for n in TENSOR_FIELDS)
            and a.settings == b.settings and a.optics == b.optics and a.frame == b.frame)


# -- loading --------------------------------------------------------------------------------

def test_presets_of_either_model_join_into_layers():
    c = load_preset("rain-heavy+fog-light")
    assert isinstance(c, CombinedPreset) and c.name == "rain-heavy+fog-light"
    assert c.layer_names == ("rain-heavy", "fog-light") and c.layer_models == ("field", "field")
    assert c.layers == (load_preset("rain-heavy"), load_preset("fog-light"))   # each as alone
    mixed = load_preset("snow + fog-light")                                   # spaces allowed
    assert mixed.name == "snow+fog-light" and mixed.layer_models == ("paper", "field")
    assert isinstance(mixed.layer(0), Preset) and isinstance(mixed.layer("fog-light"), FieldPreset)
    assert "preset snow (snow.toml)" in mixed.source


def test_a_preset_file_is_a_layer_named_by_its_stem(tmp_path):
    mine = tmp_path / "drizzle.toml"
    mine.write_text('model = "field"\ndensity = 20\ndiameter = 0.002\n')
    c = load_preset(f"{mine}+fog-light", {"drizzle.density": "30"})
    assert c.layer_names == ("drizzle", "fog-light") and c.layer(0).density == 30


def test_overrides_name_their_layer_by_name_or_position_or_apply_to_all():
    c = load_preset("snow+fog-light", {"snow.count": "500", "2.density": "0.05",
                                        "color": "255,0,0"})
    assert c.layer(0).count == 500 and c.layer(1).density == 0.05
    assert c.layer(0).color == c.layer(1).color == (255, 0, 0)
    assert c.layer(1).diameter == load_preset("fog-light").diameter   # the rest as the file says
    # a preset name with dots: the key is after the last one
    assert load_preset("motion-blur-0.0375+fog", {"motion-blur-0.0375.count": "7"}).layer(0).count == 7


def test_the_preset_dictionary_round_trips():
    c = load_preset("snow+rain-heavy", {"snow.count": "123", "rain-heavy.wind": "0.5,0"})
    again = CombinedPreset.from_dict(json.loads(json.dumps(c.to_dict())))
    assert again == c and again.layer_names == c.layer_names and again.name == c.name
    assert c.to_dict()["model"] == "combined" and len(c.to_dict()["layers"]) == 2


@pytest.mark.parametrize("name,overrides,message", [
    ("snow+", {}, "--preset snow+: layer 2 of 2 is empty"),
    ("+fog", {}, "--preset +fog: layer 1 of 2 is empty"),
    ("snow++fog", {}, "--preset snow++fog: layer 2 of 3 is empty"),
    ("snow+hail", {}, "--preset snow+hail: layer 2 (hail): unknown preset 'hail'"),
    ("snow+fog+snow", {}, "--preset snow+fog+snow: layer 'snow' is given twice"),
    ("snow+fog-light", {"count": "5"},
     "--set count: not a key of layer 2 (fog-light, a field preset); name the layer it is for, "
     "e.g. snow.count=..."),
    ("snow+fog", {"colour": "1,2,3"}, "--set colour: no layer of snow+fog has this key"),
    ("snow+fog", {"hail.count": "5"}, "--set hail.count: snow+fog has no layer 'hail'"),
    ("snow+fog", {"3.count": "5"}, "--set 3.count: snow+fog has no layer '3'"),
    ("snow+fog", {"2.size": "4"}, "--preset snow+fog: layer 2 (fog): --set: key 'size' = 4: must be an odd number"),
    ("snow-light+fog-light", {"fog-light.frame_rate": "30"},
     "--preset snow-light+fog-light: its field layers have different frame rates "
     "(frame_rate: snow-light 0, fog-light 30"),
], ids=["empty-last", "empty-first", "empty-middle", "unknown", "repeated", "key-of-one-layer",
        "key-of-no-layer", "no-such-layer", "no-such-position", "bad-value", "frame-rates"])
def test_bad_combinations_are_one_line_naming_the_option(name, overrides, message):
    with pytest.raises(ConfigError) as exc:
        load_preset(name, overrides)
    line = spelled(exc)
    assert message in line and "\n" not in line


def test_a_layer_file_with_the_name_of_another_layer_is_a_repeat(tmp_path):
    (tmp_path / "snow.toml").write_text("count = 10\n")
    with pytest.raises(ConfigError, match="layer 'snow' is given twice"):
        load_preset(f"snow+{tmp_path / 'snow.toml'}")


def test_a_file_whose_name_holds_a_plus_is_one_preset(tmp_path):
    odd = tmp_path / "snow+more.toml"
    odd.write_text("count = 10\n")
    assert isinstance(load_preset(str(odd)), Preset)


def test_every_example_combination_loads():
    assert len(EXAMPLE_COMBINATIONS) >= 4
    models = set()
    for name in EXAMPLE_COMBINATIONS:
        c = load_preset(name)
        assert isinstance(c, CombinedPreset) and c.name == name
        models |= set(c.layer_models)
    assert models == {"paper", "field"}


# -- severity ladders -----------------------------------------------------------------------

def test_severity_ladders_keep_their_ratios_in_combination(pair):
    levels = ("light", "moderate", "heavy")
    alone = [load_preset(f"snow-{lvl}") for lvl in levels]
    combined = [load_preset(f"snow-{lvl}+fog-moderate") for lvl in levels]
    for a, c in zip(alone, combined):
        assert c.layer(0) == a and c.layer(1) == load_preset("fog-moderate")
    # particles per field tile, and so per cubic metre, in the ladder's ratios
    tiles = [c.layer(0).tile_count() for c in combined]
    assert tiles == [a.tile_count() for a in alone]
    assert tiles[1] / tiles[0] == pytest.approx(alone[1].density / alone[0].density, rel=1e-3)
    assert tiles[2] / tiles[0] == pytest.approx(alone[2].density / alone[0].density, rel=1e-3)
    # the sampled layers are the presets' own particles: the same counts seen in the pair
    # (fields drawn out to 3 m, the plane's depth is 4 m: quick)
    counts = []
    for lvl in levels:
        layers = sample_weather(pair, load_preset(f"snow-{lvl}+fog-moderate", {"far": "3"}), seed=4,
                                frame_rate=RATE)
        alone_near = sample_weather(pair, load_preset(f"snow-{lvl}", {"far": "3"}),
                                    layer_seed(4, f"snow-{lvl}"), frame_rate=RATE)
        assert same_record(layers.layer(0), alone_near)
        counts.append(layers.counts[0])
    assert counts[0] < counts[1] < counts[2]


# -- sampling -------------------------------------------------------------------------------

def test_each_layer_is_its_preset_alone_with_its_own_seed(pair):
    c = load_preset("snow+fog-light", {"snow.count": "300"})
    layers = sample_layers(pair, c, seed=7, frame_rate=RATE)
    assert isinstance(layers, LayeredParticles) and layers.names == c.layer_names
    for name, preset, record in zip(c.layer_names, c.layers, layers.layers):
        assert same_record(record, sample_weather(pair, preset, layer_seed(7, name), frame_rate=RATE))
    # same seed, same particles; the order of the layers changes no layer
    again = sample_weather(pair, c, seed=7, frame_rate=RATE)
    assert all(same_record(a, b) for a, b in zip(layers.layers, again.layers))
    swapped = sample_layers(pair, load_preset("fog-light+snow", {"snow.count": "300"}), seed=7,
                            frame_rate=RATE)
    assert same_record(swapped.layer("snow"), layers.layer("snow"))
    assert same_record(swapped.layer("fog-light"), layers.layer("fog-light"))
    # explicit seeds, one per layer
    given = sample_layers(pair, c, seed=(11, 12), frame_rate=RATE)
    assert same_record(given.layer(1), sample_weather(pair, c.layer(1), 11 + 1, frame_rate=RATE))
    with pytest.raises(ConfigError, match="3 seeds for the 2 layers"):
        sample_layers(pair, c, seed=(1, 2, 3), frame_rate=RATE)


def test_layers_never_share_random_numbers(pair):
    # two paper layers of one model and count: were their seeds equal, so would their positions be
    layers = sample_layers(pair, load_preset("snow+grey", {"count": "200"}), seed=0)
    assert layers.counts == (200, 200)
    assert not torch.equal(layers.layer(0).position, layers.layer(1).position)
    assert layer_seed(0, "snow") != layer_seed(0, "grey") != layer_seed(1, "snow")


def test_the_layered_record_numbers_every_particle(pair):
    layers = sample_layers(pair, load_preset("snow+fog", {"snow.count": "30", "fog.count": "4"}), 0,
                           frame_rate=RATE)
    assert layers.counts == (30, 4) and layers.count == len(layers) == 34
    assert layers.layer_index().tolist() == [0] * 30 + [1] * 4
    assert torch.equal(layers.concat("position")[30:], layers.layer("fog").position)
    nudged = layers.replace_layer("fog", layers.layer(1).replace(
        offset1=torch.ones_like(layers.layer(1).offset1)))
    assert float(nudged.concat("offset1")[30:].min()) == 1 and float(nudged.concat("offset1")[:30].abs().max()) == 0
    assert nudged.to(dtype=torch.float64).layer(0).position.dtype == torch.float64
    with pytest.raises(KeyError, match="no layer 'rain'"):
        layers.layer("rain")
    with pytest.raises(ValueError, match="layer names must differ"):
        LayeredParticles(layers.layers, ("a", "a"))
    with pytest.raises(ValueError, match="different reference frames"):
        LayeredParticles((layers.layer(0), layers.layer(1).replace(frame="camera1")), ("a", "b"))


# -- storage --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def mixed_layers(pair):
    c = load_preset("snow+fog-light", {"snow.count": "300", "fog-light.density": "0.5"})
    layers = sample_layers(pair, c, seed=3, frame_rate=RATE)
    assert min(layers.counts) > 0
    return layers


def test_layers_round_trip_through_one_file(tmp_path, mixed_layers):
    path = mixed_layers.save(tmp_path / "pair.npz")
    again = LayeredParticles.load(path)
    assert again.names == mixed_layers.names and again.counts == mixed_layers.counts
    assert all(same_record(a, b) for a, b in zip(again.layers, mixed_layers.layers))
    assert load_particles(path).names == mixed_layers.names
    with np.load(path, allow_pickle=False) as data:
        assert int(data["format_version"]) == 4
        assert data["layer"].dtype == np.uint8
        assert data["layer"].tolist() == mixed_layers.layer_index().tolist()
        scalars = json.loads(str(data["scalars"]))        # the layers' 0-d entries, gathered
        assert scalars["layer0.format_version"][0] == 5 and scalars["layer1.format_version"][0] == 5
        assert scalars["layer1.optics"][0].startswith("{") and "layer0.optics" not in scalars
    # a single preset's record is read as before, and has no byte of layers
    single = mixed_layers.layer(0)
    plain = single.save(tmp_path / "single.npz")
    assert isinstance(load_particles(plain), Particles)
    assert not any(k.startswith("layer") for k in single.to_numpy())
    with pytest.raises(FormatError, match="holds the layers of a combined preset"):
        Particles.load(path)


@pytest.mark.parametrize("damage,message", [
    (lambda a: a.update(layer=a["layer"][::-1].copy()), "'layer' is not the layer of every particle"),
    (lambda a: a.update(layer_counts=np.array([1, 2, 3])), "'layer_counts' [1, 2, 3] does not fit"),
    (lambda a: a.pop("layer1.color"), "layer 1 (fog-light): missing array 'color'"),
    (lambda a: a.pop("layer_names"), "without 'layer_names'"),
], ids=["layer-order", "counts", "missing-array", "no-names"])
def test_a_damaged_layered_file_names_the_file_and_the_layer(tmp_path, mixed_layers, damage, message):
    arrays = mixed_layers.to_numpy()
    damage(arrays)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FormatError) as exc:
        LayeredParticles.load(tmp_path / "bad.npz")
    assert str(exc.value).startswith(str(tmp_path / "bad.npz")) and message in str(exc.value)


def test_pair_metadata_round_trips_with_layers_and_seeds(tmp_path, pair, mixed_layers):
    from weathergen.outputs.metadata import pair_metadata, read_metadata, write_metadata

    c = load_preset("snow+fog-light", {"snow.count": "300", "fog-light.density": "0.5"})
    arrays = pair_metadata(mixed_layers, pair.id, 99, c.to_dict(), c.name, layer_seeds=(5, 6))
    arrays["files"] = np.array("[]")
    path = write_metadata(tmp_path / "meta.npz", arrays)
    back = read_metadata(path)
    assert back["layer_seeds"].tolist() == [5, 6] and int(back["seed"]) == 99
    assert str(back["preset_name"]) == "snow+fog-light"
    assert CombinedPreset.from_dict(json.loads(str(back["preset"]))) == c
    again = LayeredParticles.from_arrays(back, path)
    assert all(same_record(a, b) for a, b in zip(again.layers, mixed_layers.layers))
    assert torch.equal(again.layer_index(), mixed_layers.layer_index())
