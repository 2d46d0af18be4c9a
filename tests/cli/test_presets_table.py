"""`weathergen presets`: the visibility of the air as the renderer draws it (a rain or snow rung's
veil, not its `visibility` key of 0), and only the keys that apply to each kind of preset (an
atmosphere alone lists no particle keys)."""

from __future__ import annotations

import math

import pytest
from click.testing import CliRunner

from weathergen.cli.main import _register, cli
from weathergen.cli.presets_cmd import ATMOSPHERE_KEYS
from weathergen.engine.weather.presets import field_preset_keys, load_preset

PARTICLE_KEYS = ("diameter", "templates", "fall_speed", "exposure", "blur_samples", "near", "far")


def shown(*args) -> str:
    _register()
    result = CliRunner().invoke(cli, ["presets", *args])
    assert result.exit_code == 0, result.output
    return result.output


def rows(output: str) -> dict[str, list[str]]:
    """The cells of every table row that starts a row (its first cell not empty), by that cell."""
    out = {}
    for line in output.splitlines():
        cells = [c.strip() for c in line.split("│")[1:-1]]
        if cells and cells[0]:
            out[cells[0]] = cells[1:]
    return out


def listing() -> dict[str, dict[str, str]]:
    """`weathergen presets`: each preset's row, by its name, as {column header: cell}."""
    out, header = {}, []
    for line in shown().splitlines():
        if line.startswith("┃"):
            header = [c.strip() for c in line.split("┃")[1:-1]]
        elif line.startswith("│"):
            cells = [c.strip() for c in line.split("│")[1:-1]]
            if cells[0]:
                out[cells[0]] = dict(zip(header, cells))
    return out


def marshall_palmer_visibility(rate_mm_h: float) -> float:
    """Metres: −ln(0.05) / β, β = 2.24 C^0.75 per km for rain of C = R / (3.6 · 6 m/s) g/m³."""
    beta = 2.24e-3 * (rate_mm_h / 21.6) ** 0.75
    return -math.log(0.05) / beta


def test_a_rain_rung_shows_its_veil_not_a_visibility_of_0():
    table = rows(shown("rain-heavy"))
    assert table["visibility"][0] == "0"                          # the key as written
    veil = table["(veil)"][0]
    expected = marshall_palmer_visibility(load_preset("rain-heavy").rain_rate)
    assert 1150 < expected < 1250                                 # about 1.2 km
    assert veil.startswith(f"{expected:.0f} m (β₀ ")
    assert listing()["rain-heavy"]["visibility"] == f"{expected:.0f}"


def test_a_snow_rung_shows_its_veil_and_a_fog_rung_its_own_visibility():
    listed = listing()
    column = "visibility"
    snow = load_preset("snow-heavy")
    # Stallabrass: β = 10.36 C^0.7776 per km for snow of C = R / (3.6 · 1 m/s) g/m³
    expected = -math.log(0.05) / (10.36e-3 * (snow.snow_rate / 3.6) ** 0.7776)
    assert listed["snow-heavy"][column] == f"{expected:.0f}"
    assert listed["fog-moderate"][column] == f"{load_preset('fog-moderate').visibility:.0f}"
    assert listed["sparks-heavy"][column] == "clear"


@pytest.mark.parametrize("name", ["fog-light", "fog-moderate", "fog-heavy", "mist"])
def test_an_atmosphere_alone_lists_no_particle_keys(name):
    output = shown(name)
    table = rows(output)
    for key in PARTICLE_KEYS:
        assert key not in table, key
    for key in ATMOSPHERE_KEYS:
        assert key in table, key
    assert "the particle keys do not apply" in output
    listed = listing()[name]
    for key in ("diameter", "templates", "blend", "fall m/s", "exposure s", "far"):
        assert listed[key] == "–", key
    assert listed["density"] == "0" and listed["wind"] != "–"


@pytest.mark.parametrize("name", ["snow-heavy", "rain-light", "sparks-moderate"])
def test_a_field_with_particles_lists_every_key(name):
    output = shown(name)
    table = rows(output)
    assert all(f.name in table for f in field_preset_keys())
    assert "(veil)" in table and "do not apply" not in output


def test_a_combined_preset_shows_each_layer_by_its_kind():
    output = shown("rain-heavy+fog-light")
    rain, fog = output.split("layer 2 of")
    assert "diameter" in rows(rain) and "diameter" not in rows(fog)
    assert rows(fog)["(veil)"][0].startswith("1000 m")
