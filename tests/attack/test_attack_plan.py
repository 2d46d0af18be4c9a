"""The precedence rules of an attack request (weathergen.attack.plan), without the command line."""

from __future__ import annotations

import json

import pytest

from weathergen.attack import (ATTACK_CONFIGS, LR_APPEARANCE, LR_POSITIONS, OPTIMIZABLE,
                               default_evaluation_path)
from weathergen.attack.plan import attack_pass_name, default_attack_out, plan_attack
from weathergen.engine import BETA_ATTACK, BETA_RENDER, load_preset
from weathergen.errors import ConfigError


def stored_output(folder, name):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "manifest.json").write_text(json.dumps({"preset_name": name,
                                                      "preset": load_preset(name).to_dict()}))
    return folder


def test_no_option_attacks_snow_with_its_configuration():
    plan = plan_attack()
    assert (plan.preset_name, plan.label, plan.config) == ("snow", "snow", ATTACK_CONFIGS["snow"])
    assert plan.settings.optimize == OPTIMIZABLE
    assert plan.settings.learning_rates["positions"] == LR_POSITIONS and plan.settings.beta == BETA_RENDER


def test_a_configuration_sets_preset_variables_and_occlusion():
    plan = plan_attack("fog")
    assert plan.preset_name == "fog" and plan.preset.name == "fog"
    assert plan.settings.optimize == ("offset1", "color", "transparency")
    assert plan.settings.beta == BETA_ATTACK


def test_explicit_values_win_over_the_configuration():
    plan = plan_attack("grey-color", preset="snow")
    assert (plan.preset_name, plan.label, plan.settings.optimize) == ("snow", "grey-color", ("color",))
    assert plan_attack("fog", occlusion_gradient=False).settings.beta == BETA_RENDER
    assert plan_attack("snow", lr=0.5).settings.lr == 0.5
    # Other variables than the configuration's: its learning rate no longer applies.
    plan = plan_attack("fog", optimize="color")
    assert plan.settings.lr is None and plan.settings.learning_rates == {"color": LR_APPEARANCE}
    assert plan.settings.beta == BETA_ATTACK
    assert plan_attack(optimize=["transparency", "color"]).settings.optimize == ("color", "transparency")


def test_a_preset_without_configuration_frees_everything():
    plan = plan_attack(preset="grey", steps=3, alpha1=1.0, alpha2=2.0)
    assert plan.config is None and plan.label == "grey"
    assert plan.settings.optimize == OPTIMIZABLE and plan.settings.lr is None
    assert (plan.settings.steps, plan.settings.alpha1, plan.settings.alpha2) == (3, 1.0, 2.0)


def test_stored_particles_pick_their_preset_and_its_configuration(tmp_path):
    fog = stored_output(tmp_path / "fog", "fog")
    plan = plan_attack(particles_from=fog)
    assert plan.preset_name == "fog" and "offset2" not in plan.settings.optimize
    assert plan.settings.beta == BETA_ATTACK
    with pytest.raises(ConfigError, match="^preset snow: the particles in .* were sampled from 'fog'"):
        plan_attack(preset="snow", particles_from=fog)
    with pytest.raises(ConfigError, match="^overrides cannot change stored particles"):
        plan_attack(overrides={"blend": "alpha"}, particles_from=fog)


def test_unknown_names_are_refused():
    with pytest.raises(ConfigError, match="hail"):
        plan_attack("hail")
    with pytest.raises(ConfigError, match="^optimize: unknown variable"):
        plan_attack(optimize="wind")


def test_defaults():
    assert default_attack_out("fog").as_posix() == "out/attack-fog"
    assert attack_pass_name("fog", "clean") == "fog_adv_clean"
    assert default_evaluation_path("out/snow", "raft-small").as_posix() == "out/snow/evaluate-raft-small.json"
