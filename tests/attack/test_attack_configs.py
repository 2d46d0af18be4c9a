"""Attack configurations are data: the bundled table, its checks, and what reads it."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from weathergen.attack import ATTACK_CONFIGS, LR_APPEARANCE, OPTIMIZABLE, default_lr
from weathergen.attack.configs import parse_configs
from weathergen.errors import ConfigError


def test_the_bundled_table_is_the_supplements_in_its_order():
    assert list(ATTACK_CONFIGS) == ["grey-offset1", "grey-offset2", "grey-color",
                                    "grey-transparency", "grey-offsets", "grey-appearance",
                                    "grey-all", "snow", "rain", "sparks", "fog"]
    assert all(c.lr == default_lr(c.optimize) for c in ATTACK_CONFIGS.values())
    assert [n for n, c in ATTACK_CONFIGS.items() if c.occlusion_gradient] == ["fog"]
    assert ATTACK_CONFIGS["grey-offsets"].optimize == ("offset1", "offset2")


def test_a_table_makes_a_configuration():
    configs = parse_configs('[hail]\npreset = "snow"\noptimize = ["transparency", "color"]\n'
                            'lr = 0.01\ndescription = "hail"\n', "hail.toml")
    hail = configs["hail"]
    assert (hail.preset, hail.optimize, hail.lr, hail.occlusion_gradient) == \
        ("snow", ("color", "transparency"), 0.01, False)
    default = parse_configs('[tint]\npreset = "grey"\noptimize = ["color"]\n', "t.toml")["tint"]
    assert default.lr == LR_APPEARANCE


@pytest.mark.parametrize("text,message", [
    ('[x]\npreset = "snow"\noptimize = ["wind"]\n', r"x\.toml: \[x\]: 'optimize' must list"),
    ('[x]\npreset = "snow"\noptimize = []\n', r"'optimize' must list"),
    ('[x]\noptimize = ["color"]\n', r"\[x\]: 'preset' must name a preset"),
    ('[x]\npreset = "snow"\noptimize = ["color"]\nlr = -1\n', r"'lr' must be a positive number"),
    ('[x]\npreset = "snow"\noptimize = ["color"]\nsteps = 3\n', r"unknown key\(s\) steps"),
    ('[x]\npreset = "snow"\noptimize = ["color"]\nocclusion_gradient = 1\n', r"true or false"),
    ('x = 1\n', r"\[x\]: expected a table"),
    ('[x\n', r"x\.toml: not valid TOML"),
])
def test_bad_tables_are_refused_naming_file_and_table(text, message):
    with pytest.raises(ConfigError, match=message):
        parse_configs(text, "x.toml")


def test_attack_help_lists_every_configuration():
    from weathergen.cli.main import cli

    result = CliRunner().invoke(cli, ["attack", "--help"], terminal_width=400)
    assert result.exit_code == 0
    assert f"supplement ({', '.join(ATTACK_CONFIGS)})" in " ".join(result.output.split())
    assert set(OPTIMIZABLE) >= set(ATTACK_CONFIGS["fog"].optimize)
