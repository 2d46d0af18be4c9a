"""The attack on combined weather: every layer drawn in one pass, some layers' particles or all
optimised (``--optimize-layer``), the output re-rendered from its stored layers."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from weathergen.attack import AttackSettings, TargetSpec, attack_pair
from weathergen.attack.plan import plan_attack
from weathergen.engine import LayeredParticles, load_preset, sample_weather
from weathergen.engine.records.particles import TENSOR_FIELDS
from weathergen.errors import ConfigError


@pytest.fixture(scope="module")
def small_pair():
    from weathergen.datasets import demo_pairs

    pair = demo_pairs(scenes=["courtyard"], frames_per_scene=1)[0]
    rows, cols = slice(40, 136), slice(120, 248)
    k = pair.intrinsics.clone()
    k[0, 2] -= 120
    k[1, 2] -= 40
    crop = lambda t: None if t is None else t[:, rows, cols].contiguous()  # noqa: E731
    return dataclasses.replace(pair, image1=crop(pair.image1), image2=crop(pair.image2),
                               depth1=crop(pair.depth1), depth2=crop(pair.depth2),
                               flow=crop(pair.flow), flow_valid=crop(pair.flow_valid),
                               intrinsics=k).validate()


@pytest.fixture(scope="module")
def raft_small(raft_small_weights):
    from weathergen.models import get_model

    return get_model("raft-small", checkpoint=raft_small_weights, iters=2)


@pytest.fixture(scope="module")
def layers(small_pair):
    preset = load_preset("grey+fog", {"grey.count": 60, "fog.count": 4})
    return sample_weather(small_pair, preset, seed=2)


def changed(a, b) -> set:
    return {n for n in TENSOR_FIELDS if not torch.equal(getattr(a, n), getattr(b, n))}


@pytest.mark.parametrize("which", [("fog",), None], ids=["one-layer", "all-layers"])
def test_the_attack_moves_the_freed_layers_only(raft_small, small_pair, layers, which):
    settings = AttackSettings(optimize=("offset1", "color"), steps=3, lr=1e-2, layers=which)
    result = attack_pair(raft_small, small_pair, layers, settings, TargetSpec("zero"))
    best = result.best_particles
    assert isinstance(best, LayeredParticles) and best.names == layers.names
    assert result.best_step > 0
    grey, fog = (changed(b, a) for a, b in zip(layers.layers, best.layers))
    assert fog == {"offset1", "color"}
    assert grey == (set() if which == ("fog",) else {"offset1", "color"})


def test_optimize_layer_is_checked_against_the_preset():
    plan = plan_attack(preset="snow+fog-light", layers="fog-light")
    assert plan.settings.layers == ("fog-light",)
    assert plan_attack(preset="snow+fog-light", layers="all").settings.layers is None
    assert plan.settings.to_dict()["layers"] == ["fog-light"]
    with pytest.raises(ConfigError, match="no such layer of snow.fog-light"):
        plan_attack(preset="snow+fog-light", layers="rain")
    with pytest.raises(ConfigError, match="applies to combined presets"):
        plan_attack(preset="snow", layers="snow")
    # the θ bound of the combination is its layers' largest (sparks: 1.5)
    assert plan_attack(preset="snow+sparks").settings.transparency_max == 1.5


@pytest.mark.slow
def test_attack_cli_on_a_combination_writes_layers_that_rerender(tmp_path, raft_small_weights):
    from weathergen.cli.main import _register, cli
    from weathergen.engine import load_particles
    from weathergen.io.images import read_image

    _register()
    out, again = tmp_path / "attack", tmp_path / "again"
    one = ["--scenes", "courtyard", "--frames-per-scene", "1"]
    res = CliRunner().invoke(cli, ["attack", "--model", "raft-small", "--checkpoint",
                                   str(raft_small_weights), "--iters", "2", *one, "--steps", "2",
                                   "--preset", "snow+fog-light", "--set", "snow.count=100",
                                   "--optimize-layer", "snow", "--out", str(out)])
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["attack"]["layers"] == ["snow"]
    npz = out / "training" / "particles" / "courtyard_0001" / "frame_0001.npz"
    stored = load_particles(npz)
    assert stored.names == ("snow", "fog-light")
    res = CliRunner().invoke(cli, ["render", "--particles", str(out), *one, "--out", str(again)])
    assert res.exit_code == 0, res.output
    for name in ("frame_0001.png", "frame_0002.png"):
        attacked = read_image(out / "training" / "snow+fog-light_adv_clean" / "courtyard_0001" / name)
        rendered = read_image(again / "training" / "snow+fog-light_clean" / "courtyard_0001" / name)
        assert np.abs(attacked - rendered).max() <= 1.5 / 255
