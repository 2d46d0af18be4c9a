"""Presets: every table row loads; validation errors name file, key and value; the CLI."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from weathergen.engine.presets import Preset, list_presets, load_preset, parse_override
from weathergen.errors import ConfigError

TABLE_ROWS = (
    ["snow", "rain", "sparks", "fog", "grey"]
    + [f"particles-{n}" for n in (1000, 2000, 3000, 4000, 5000)]
    + [f"motion-blur-{x}" for x in ("0.0", "0.0375", "0.075", "0.1125", "0.15")]
    + [f"{mode}-{c}" for mode in ("additive", "alpha")
       for c in ("white", "red", "green", "blue", "color")]
    + [f"size-{s}" for s in ("small", "medium", "large", "fog")]
)


def test_every_table_row_is_a_preset():
    assert sorted(TABLE_ROWS) == list_presets()


@pytest.mark.parametrize("name", TABLE_ROWS)
def test_preset_loads_and_validates(name):
    p = load_preset(name)
    assert isinstance(p, Preset) and p.name == name
    assert p.size % 2 == 1 and p.count > 0
    d = p.to_dict()
    assert d["name"] == name and d["count"] == p.count


@pytest.mark.parametrize("alias,original", [("particles-3000", "snow"), ("motion-blur-0.15", "rain"),
                                            ("additive-red", "sparks"), ("size-fog", "fog")])
def test_aliases_match_their_main_preset(alias, original):
    a, b = load_preset(alias).to_dict(), load_preset(original).to_dict()
    for key in ("name", "source", "description"):
        a.pop(key), b.pop(key)
    assert a == b


def test_mislabelled_motion_columns_are_read_by_meaning():
    rain, sparks = load_preset("rain"), load_preset("sparks")
    assert (rain.motion_scale_jitter, rain.motion_angle_jitter) == (0.1, 4.0)
    assert (sparks.motion_scale_jitter, sparks.motion_angle_jitter) == (0.2, 60.0)


def test_table_values_of_main_presets():
    snow, rain, sparks, fog = (load_preset(n) for n in ("snow", "rain", "sparks", "fog"))
    assert (snow.count, snow.size, snow.depth_decay, snow.blend, snow.motion_y) == \
        (3000, 71, 9.0, "additive", 0.2)
    assert (rain.size, rain.blur_length, rain.blur_samples, rain.motion_blur) == (51, 0.15, 20, True)
    assert sparks.color == (191, 79, 64) and sparks.hue_jitter == 15 and sparks.motion_y == -0.05
    assert (fog.count, fog.size, fog.templates, fog.blend) == (60, 451, "dust", "alpha")
    assert fog.transparency_mode == "constant" and fog.transparency == 0.25
    assert load_preset("size-large").transparency_mode == "depth"


def test_overrides_are_parsed_per_type_and_win_over_the_file():
    p = load_preset("snow", overrides={"count": "500", "color": "10,20,30", "blend": "alpha",
                                       "motion_blur": "true", "blur_length": "0.1"})
    assert (p.count, p.color, p.blend, p.motion_blur, p.blur_length) == \
        (500, (10, 20, 30), "alpha", True, 0.1)
    assert parse_override("volume_z", "[0.5, 2]") == (0.5, 2.0)


def test_user_preset_file_and_defaults(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text('count = 12\ntemplates = "shapes"\n')
    p = load_preset(f)
    assert p.count == 12 and p.size == Preset().size  # missing keys take schema defaults
    assert p.templates == str(tmp_path / "shapes")     # relative folders resolve to the file
    assert load_preset(str(f), overrides={"count": 3}).count == 3


@pytest.mark.parametrize("text,key,value", [
    ("size = 70", "size", "70"),
    ("count = -1", "count", "-1"),
    ("color = [255, 300, 0]", "color", "300"),
    ("blur_samples = 0", "blur_samples", "0"),
    ("blend = 'screen'", "blend", "screen"),
    ("count = 'many'", "count", "many"),
    ("snowiness = 3", "snowiness", "snowiness"),
    ("volume_z = [3, 0]", "volume_z", "[3, 0]"),
    ("transparency = -0.5", "transparency", "-0.5"),
])
def test_invalid_preset_names_file_key_and_value(tmp_path, text, key, value):
    f = tmp_path / "bad.toml"
    f.write_text(text + "\n")
    with pytest.raises(ConfigError) as err:
        load_preset(f)
    msg = str(err.value)
    assert str(f) in msg and f"'{key}'" in msg and value in msg


def test_invalid_override_and_unknown_preset():
    with pytest.raises(ConfigError, match=r"--set: key 'size' = 8"):
        load_preset("snow", overrides={"size": "8"})
    with pytest.raises(ConfigError, match="unknown key 'sizee'"):
        load_preset("snow", overrides={"sizee": "8"})
    with pytest.raises(ConfigError) as err:
        load_preset("hail")
    assert "unknown preset 'hail'" in str(err.value) and "snow" in str(err.value)


def test_blur_needs_a_length(tmp_path):
    f = tmp_path / "streaks.toml"
    f.write_text("motion_blur = true\nblur_length = 0.0\n")
    with pytest.raises(ConfigError, match="blur_length"):
        load_preset(f)


def test_broken_toml(tmp_path):
    f = tmp_path / "broken.toml"
    f.write_text("count = = 3\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_preset(f)


@pytest.fixture
def cli():
    from weathergen.cli import presets_cmd  # noqa: F401  (registers the command)
    from weathergen.cli.main import cli
    return cli


def test_cli_lists_presets(cli):
    result = CliRunner().invoke(cli, ["presets"])
    assert result.exit_code == 0, result.output
    for name in ("snow", "rain", "sparks", "fog", "alpha-color", "size-medium"):
        assert name in result.output


def test_cli_shows_one_preset_resolved(cli):
    result = CliRunner().invoke(cli, ["presets", "rain", "--set", "count=123"])
    assert result.exit_code == 0, result.output
    assert "123" in result.output and "blur_samples" in result.output


def test_cli_errors_are_one_line(cli):
    result = CliRunner().invoke(cli, ["presets", "hail"])
    assert result.exit_code == 2
    assert "unknown preset 'hail'" in result.output and "Traceback" not in result.output
    result = CliRunner().invoke(cli, ["presets", "snow", "--set", "size=4"])
    assert result.exit_code == 2 and "'size'" in result.output
