"""Presets: every table row loads; validation errors name file, key and value; the CLI."""

from __future__ import annotations

import pytest
from click.testing import CliRunner

from weathergen.engine.weather.presets import Preset, list_presets, load_preset, parse_override
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
    assert sorted(TABLE_ROWS) == list_presets("paper")


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


# The supplement's table "Particle configurations", transcribed by hand from the paper, one row
# per preset: count, size, d-decay, templates, RGB, (dH, dL, dS), mode, theta, m_y, then the two
# motion columns as printed (labelled "angle" and "norm", but holding the scale fraction and the
# angle in degrees), blur, length, blur particles.
_WHITE, _NO_JITTER, _JITTER = (255, 255, 255), (0, 0.0, 0.0), (15, 0.1, 0.1)
_SNOW = (3000, 71, 9, "particles", _WHITE, _NO_JITTER, "additive", 0.75, 0.2, 0.0, 0, False, 0.0, 0)
_SPARKS = (3000, 41, 9, "particles", (191, 79, 64), _JITTER, "additive", 1.5, -0.05, 0.2, 60, True,
           0.3, 10)
_FOG = (60, 451, 0.8, "dust", _WHITE, _NO_JITTER, "Meshkin", 0.25, 0.0, 0.0, 0, False, 0.0, 0)
_COLOURS = {"white": (_WHITE, _NO_JITTER), "red": ((191, 79, 64), _JITTER),
            "green": ((79, 191, 64), _JITTER), "blue": ((64, 79, 191), _JITTER),
            "color": ((205, 80, 80), (180, 0.1, 0.1))}
PAPER_TABLE = {
    **{f"particles-{n}": (n,) + _SNOW[1:] for n in (1000, 2000, 3000, 4000, 5000)},
    "snow": _SNOW,
    "grey": (3000, 71, 9, "particles", (127, 127, 127), _NO_JITTER, "Meshkin", 0.75, 0.2, 0.0, 0,
             False, 0.0, 0),
    "motion-blur-0.0": _SNOW,
    **{f"motion-blur-{length}": (3000, size, 9, "particles", _WHITE, _NO_JITTER, "additive", 0.75,
                                 0.2, 0.1, 4, True, float(length), 20)
       for length, size in (("0.0375", 67), ("0.075", 61), ("0.1125", 57), ("0.15", 51))},
    "rain": (3000, 51, 9, "particles", _WHITE, _NO_JITTER, "additive", 0.75, 0.2, 0.1, 4, True,
             0.15, 20),
    **{f"{mode}-{name}": (3000, 41, 9, "particles", rgb, hls, table_mode, 1.5, -0.05, 0.2, 60, True,
                          0.3, 10)
       for mode, table_mode in (("additive", "additive"), ("alpha", "Meshkin"))
       for name, (rgb, hls) in _COLOURS.items()},
    "sparks": _SPARKS,
    "size-small": (3000, 71, 9, "dust", _WHITE, _NO_JITTER, "Meshkin", 1.0, 0.0, 0.0, 0, False,
                   0.0, 0),
    "size-medium": (141, 161, 1.75, "dust", _WHITE, _NO_JITTER, "Meshkin", 0.78, 0.0, 0.0, 0, False,
                    0.0, 0),
    "size-large": (60, 451, 0.8, "dust", _WHITE, _NO_JITTER, "Meshkin", 0.1, 0.0, 0.0, 0, False,
                   0.0, 0),
    "size-fog": _FOG,
    "fog": _FOG,
}


def test_the_transcribed_table_covers_every_preset():
    assert sorted(PAPER_TABLE) == list_presets("paper")


@pytest.mark.parametrize("name", sorted(PAPER_TABLE))
def test_preset_matches_its_row_of_the_paper_table(name):
    (count, size, decay, templates, rgb, hls, mode, theta, m_y, col_angle, col_norm, blur, length,
     samples) = PAPER_TABLE[name]
    p = load_preset(name)
    assert (p.count, p.size, p.depth_decay) == (count, size, decay)
    assert p.templates == {"particles": "flakes", "dust": "dust"}[templates]
    assert p.color == rgb and (p.hue_jitter, p.lightness_jitter, p.saturation_jitter) == hls
    assert p.blend == {"additive": "additive", "Meshkin": "alpha"}[mode]
    assert p.motion_y == m_y
    # the mislabelled columns: "angle" holds the scale fraction, "norm" the angle in degrees
    assert (p.motion_scale_jitter, p.motion_angle_jitter) == (col_angle, col_norm)
    assert p.motion_blur is blur
    if blur:
        assert (p.blur_length, p.blur_samples, p.blur_sample_count) == (length, samples, samples)
    else:
        assert (p.effective_blur_length, p.blur_sample_count) == (0.0, 1)
    # every row, fog too, scales the depth hat by the table's column (fog: 0.25; the caption's
    # "depth-constant 0.3" was never what the research code rendered, see docs/engine.md)
    assert (p.transparency_mode, p.transparency) == ("depth", theta)


def test_overrides_are_parsed_per_type_and_win_over_the_file():
    p = load_preset("snow", overrides={"count": "500", "color": "10,20,30", "blend": "alpha",
                                       "motion_blur": "true", "blur_length": "0.1"})
    assert (p.count, p.color, p.blend, p.motion_blur, p.blur_length) == \
        (500, (10, 20, 30), "alpha", True, 0.1)
    assert parse_override("volume_z", "[0.5, 2]") == (0.5, 2.0)


def _png_folder(folder):
    import cv2
    import numpy as np
    folder.mkdir()
    (folder / "blob.png").write_bytes(cv2.imencode(".png", np.full((9, 9), 255, np.uint8))[1])
    return folder


def test_user_preset_file_and_defaults(tmp_path):
    _png_folder(tmp_path / "shapes")
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
    with pytest.raises(ConfigError, match=r"^overrides: key 'size' = 8") as bad:
        load_preset("snow", overrides={"size": "8"})
    assert bad.value.render(lambda name: "--set").startswith("--set: key 'size' = 8")
    with pytest.raises(ConfigError, match="unknown key 'sizee'"):
        load_preset("snow", overrides={"sizee": "8"})
    with pytest.raises(ConfigError) as err:
        load_preset("hail")
    assert "unknown preset 'hail'" in str(err.value) and "snow" in str(err.value)


def test_keys_of_both_models_are_declared_once():
    """The keys the paper's presets and the weather fields share have one declaration: the same
    default, the same check and the same place in `weathergen presets`."""
    from weathergen.engine.weather.presets import SHARED_KEYS, field_preset_keys, preset_keys

    paper = {f.name: f for f in preset_keys()}
    field = {f.name: f for f in field_preset_keys()}
    assert set(paper) & set(field) == set(SHARED_KEYS)
    for name in SHARED_KEYS:
        a, b = paper[name], field[name]
        assert a.default == b.default == SHARED_KEYS[name][0]
        assert a.metadata["check"] is b.metadata["check"] is SHARED_KEYS[name][1]
        assert a.metadata["main"] == b.metadata["main"]
        assert a.metadata["doc"] and b.metadata["doc"]
    # a shared check is the one both models run: an out-of-range value fails alike
    for model in ("snow", "snow-light"):
        with pytest.raises(ConfigError, match="hue_jitter"):
            load_preset(model, {"hue_jitter": "181"})


def test_template_folder_problems_name_the_key_at_load_time(tmp_path):
    (tmp_path / "empty").mkdir()
    f = tmp_path / "mine.toml"
    f.write_text('templates = "empty"\n')
    with pytest.raises(ConfigError) as err:
        load_preset(f)
    assert str(f) in str(err.value) and "'templates'" in str(err.value)
    assert "no PNG" in str(err.value)
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "readme.txt").write_text("not an image")
    with pytest.raises(ConfigError, match=r"^overrides: key 'templates' = .*readme.txt.*not a PNG"):
        load_preset("snow", overrides={"templates": str(notes)})
    with pytest.raises(ConfigError, match="does not exist"):
        load_preset("snow", overrides={"templates": str(tmp_path / "nowhere")})
    assert load_preset("snow", overrides={"templates": str(_png_folder(tmp_path / "ok"))})


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
    for name in TABLE_ROWS:  # every name in full, none cut short by the table layout
        assert f" {name} " in result.output, name
    assert "const" not in result.output  # every paper preset scales θ by the depth hat


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
    result = CliRunner().invoke(cli, ["presets", "snow", "--set", "templates=/nonexistent/x"])
    assert result.exit_code == 2 and "'templates'" in result.output
    assert len(result.output.strip().splitlines()) == 1


def test_presets_are_grouped_as_the_paper_presents_them(cli):
    """The paper's four weathers, its ablation variants (every other paper preset, by the
    parameter it varies), the field ladders (each weather light, moderate, heavy): every bundled
    preset in exactly one group, and `weathergen presets` lists them in that order."""
    from weathergen.engine.weather.preset_groups import preset_groups
    from weathergen.engine.weather.presets import list_presets

    groups = preset_groups()
    assert [g.title for g in groups][:3] == ["the paper's four weathers",
                                             "the paper's ablation variants (its particle configurations)",
                                             "weather fields: severity ladders"]
    assert all(g.title.startswith("other ") for g in groups[3:])     # e.g. mist, an atmosphere alone
    weathers, variants, ladders = groups[:3]
    assert weathers.names == ("snow", "rain", "sparks", "fog")
    named = [n for g in groups for n in g.names]
    assert sorted(named) == sorted(list_presets()) and len(named) == len(set(named))
    varies = dict(zip(variants.names, variants.varies))
    assert {n for n in varies if n.startswith("motion-blur-")} == {f"motion-blur-{x}" for x in
                                                                 ("0.0", "0.0375", "0.075", "0.1125", "0.15")}
    assert varies["particles-1000"] == "count" and varies["size-fog"] == "size"
    assert varies["additive-red"] == "colour, additive" and varies["alpha-red"] == "colour, alpha"
    assert varies["grey"].startswith("grey")
    assert ladders.names[:3] == ("snow-light", "snow-moderate", "snow-heavy")
    assert ladders.names[-1] == "fog-heavy" and len(ladders.names) == 12
    out = CliRunner().invoke(cli, ["presets"]).output
    places = [out.index(g.title) for g in groups] + [out.index("combined presets")]
    assert places == sorted(places)
    assert out.index(" snow ") < out.index(" particles-1000 ") < out.index(" snow-light ")


# -- plausible ranges of keys in physical units -----------------------------------------------------

def test_every_numeric_field_key_declares_its_plausible_range():
    """A key in physical units carries a Plausible range where it is declared, a dimensionless one
    says UNITLESS: a new key must say which it is."""
    from weathergen.engine.weather.presets import UNITLESS, Plausible, PlausibleBy, field_preset_keys

    for f in field_preset_keys():
        if isinstance(f.default, (bool, str)):
            continue
        plausible = f.metadata.get("plausible")
        assert plausible is UNITLESS or isinstance(plausible, (Plausible, PlausibleBy)), f.name


def test_every_bundled_field_preset_lies_in_the_plausible_ranges():
    from weathergen.engine.weather.presets import Plausible, PlausibleBy, field_preset_keys

    for name in list_presets("field"):
        p = load_preset(name)
        for f in field_preset_keys():
            plausible = f.metadata.get("plausible")
            if isinstance(plausible, PlausibleBy):
                plausible = plausible.range_for(p)
            if isinstance(plausible, Plausible):
                values = getattr(p, f.name)
                for v in values if isinstance(values, tuple) else (values,):
                    assert plausible.problem(v) is None, (name, f.name, v)


@pytest.mark.parametrize("key, value, message", [
    ("diameter", "8", "8 m is outside the plausible 0.0001 to 0.1 m for particles (flakes "
                      "templates); did you mean 0.008 m (8 mm)?"),
    ("fall_speed", "100", "100 m/s is outside the plausible -60 to 60 m/s; did you mean 27.78 m/s "
                          "(100 km/h)?"),
    ("wind", "[0, -90]", "-90 m/s is outside the plausible -60 to 60 m/s; did you mean -25 m/s "
                         "(-90 km/h)?"),
    ("near", "150", "150 m is outside the plausible 0.01 to 100 m; did you mean 0.15 m (150 mm)?"),
    ("aperture", "4", "4 m is outside the plausible 0 to 0.5 m; did you mean 0.004 m (4 mm)?"),
    ("density", "1e6", "1e+06 per m³ is outside the plausible 0.001 to 100000 per m³ (or 0)"),
    ("frame_rate", "0.5", "0.5 fps is outside the plausible 1 to 1000 fps (or 0)"),
])
def test_a_value_outside_its_plausible_range_names_key_range_and_slip(key, value, message):
    with pytest.raises(ConfigError) as caught:
        load_preset("snow-moderate", {key: value})
    assert str(caught.value).split(f"key '{key}' = ", 1)[1].split(": ", 1)[1] == message


def test_a_slip_beyond_the_keys_hard_limit_is_named_too():
    with pytest.raises(ConfigError, match=r"key 'exposure' = 16\.7: must lie in \[0, 10\]; did you "
                                          r"mean 0\.0167 s \(16\.7 ms\)\?"):
        load_preset("rain-moderate", {"exposure": "16.7"})


def test_the_diameters_range_follows_the_templates():
    haze = {"templates": "haze", "density": "0.01"}                          # wisps of haze
    assert load_preset("fog-light", {**haze, "diameter": "20"}).diameter == 20
    with pytest.raises(ConfigError, match="0.1 to 100 m for clouds"):
        load_preset("fog-light", {**haze, "diameter": "0.01"})
    with pytest.raises(ConfigError, match="for particles"):
        load_preset("snow-moderate", {"diameter": "4"})


def test_zero_is_allowed_where_it_is_a_switch():
    assert load_preset("snow-moderate", {"frame_rate": "0", "exposure": "0",
                                         "aperture": "0"}).frame_rate == 0


def test_an_override_cannot_change_a_presets_model():
    with pytest.raises(ConfigError, match="snow is a paper preset, and an override cannot change "
                                          "its model"):
        load_preset("snow", {"model": "field"})
    assert load_preset("snow", {"model": "paper"}).count == 3000
    with pytest.raises(ConfigError, match=r"layer 2 \(fog-light\): .*fog-light is a field preset"):
        load_preset("snow+fog-light", {"fog-light.model": "paper"})
