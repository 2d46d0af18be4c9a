"""The rules of a render request (weathergen.render.plan), without the command line."""

from __future__ import annotations

import json

import pytest

from weathergen.engine import APPEARANCE_KEYS, load_preset
from weathergen.errors import ConfigError, FormatError
from weathergen.render.plan import default_batch_size, default_out, default_pass_name, resolve_preset


def stored_output(folder, name, **overrides):
    """A folder whose manifest says its particles were sampled from preset ``name``."""
    folder.mkdir(parents=True, exist_ok=True)
    preset = load_preset(name, {k: str(v) for k, v in overrides.items()})
    (folder / "manifest.json").write_text(json.dumps({"preset_name": name,
                                                      "preset": preset.to_dict()}))
    return folder


def test_a_preset_by_name_with_overrides():
    preset, name, appearance = resolve_preset("rain", overrides={"count": "12"})
    assert (name, preset.count, appearance) == ("rain", 12, {})
    assert preset.blend == load_preset("rain").blend


def test_a_preset_file_replaces_the_name(tmp_path):
    path = tmp_path / "drizzle.toml"
    path.write_text("count = 5\nblend = 'alpha'\n")
    preset, name, _ = resolve_preset("snow", preset_file=path)
    assert (name, preset.count, preset.blend) == ("drizzle", 5, "alpha")


def test_stored_particles_fix_the_preset(tmp_path):
    folder = stored_output(tmp_path / "old", "rain", count=7)
    preset, name, appearance = resolve_preset("snow", overrides={}, particles_from=folder)
    assert (name, preset.count, appearance) == ("rain", 7, {})


def test_only_appearance_keys_change_stored_particles(tmp_path):
    folder = stored_output(tmp_path / "old", "snow")
    _, name, appearance = resolve_preset(overrides={"motion_blur": "true", "blur_length": "0.5",
                                                    "blur_samples": "4"}, particles_from=folder)
    assert name == "snow"
    assert appearance == {"blend": "additive", "blur_length": 0.5, "blur_samples": 4,
                          "defocus_brighten": True, "coarse": True}
    with pytest.raises(ConfigError, match="^overrides count: fixed by the stored particles") as bad:
        resolve_preset(overrides={"count": "5"}, particles_from=folder)
    assert all(key in str(bad.value) for key in APPEARANCE_KEYS)


def test_stored_particles_need_a_manifest(tmp_path):
    with pytest.raises(ConfigError, match="manifest.json: not found; particles_from takes"):
        resolve_preset(particles_from=tmp_path)
    (tmp_path / "manifest.json").write_text('{"preset_name": "snow"}')
    with pytest.raises(FormatError, match="manifest.json: not a weathergen render manifest"):
        resolve_preset(particles_from=tmp_path)


def test_defaults():
    assert default_out("snow").as_posix() == "out/snow"
    assert default_pass_name("snow", "final") == "snow_final"
    assert default_batch_size("cpu") == 1 and default_batch_size("cuda:1") == 8
