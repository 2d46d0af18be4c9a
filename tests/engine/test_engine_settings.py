"""The render-settings record: made from a preset, carried by the particles, stored once."""

from __future__ import annotations

import json
import numpy as np
import pytest

from weathergen.engine import Particles, RenderSettings, empty_particles, load_preset, load_templates
from weathergen.engine.records.settings import APPEARANCE_FIELDS, APPEARANCE_KEYS
from weathergen.errors import FormatError


def test_settings_come_from_the_preset():
    rain = load_preset("rain", {"motion_blur": "true", "blur_length": "0.4", "blur_samples": "6",
                                "blend": "alpha", "defocus_brighten": "false"})
    lib = load_templates(rain.templates)
    s = RenderSettings.from_preset(rain, lib)
    assert s == RenderSettings(blend="alpha", blur_length=0.4, blur_samples=6,
                               defocus_brighten=False, templates=lib.name,
                               templates_digest=lib.digest)
    # Motion blur off: one sample and no streak, whatever the other keys say.
    still = RenderSettings.from_preset(load_preset("rain", {"motion_blur": "false",
                                                            "blur_samples": "6"}))
    assert (still.blur_samples, still.blur_length, still.templates_digest) == (1, 0.0, "")


def test_appearance_is_what_may_change_on_re_rendering():
    s = RenderSettings(blend="alpha", blur_length=0.5, blur_samples=3)
    assert tuple(s.appearance()) == APPEARANCE_FIELDS
    assert set(APPEARANCE_FIELDS) <= set(APPEARANCE_KEYS) | {"blur_length"}
    assert s.replace(blend="additive").blend == "additive" and s.blend == "alpha"


def test_the_particle_file_stores_the_settings_once_and_reads_them_back(tmp_path):
    settings = RenderSettings(blend="alpha", blur_length=0.25, blur_samples=4,
                              defocus_brighten=False, templates="dust", templates_digest="ab12")
    path = empty_particles("camera1", settings).save(tmp_path / "p.npz")
    with np.load(path) as data:
        scalars = list(json.loads(str(data["scalars"])))
    # The 0-d entries (and their order, hence the bytes) are those of the format: the reference
    # frame, then each setting once.
    assert scalars == ["frame", "blend", "blur_length", "blur_samples", "defocus_brighten",
                       "templates", "templates_digest"]
    back = Particles.load(path)
    assert back.settings == settings and back.frame == "camera1"
    assert isinstance(back.settings.blur_samples, int) and isinstance(back.settings.blur_length, float)


def test_a_file_without_a_setting_or_with_a_bad_one_is_refused(tmp_path):
    arrays = empty_particles().to_numpy()
    for drop, message in (("blur_samples", "missing field 'blur_samples'"),):
        broken = {k: v for k, v in arrays.items() if k != drop}
        np.savez(tmp_path / "a.npz", **broken)
        with pytest.raises(FormatError, match=rf"a\.npz: {message}"):
            Particles.load(tmp_path / "a.npz")
    np.savez(tmp_path / "b.npz", **{**arrays, "blend": np.array("glow")})
    with pytest.raises(FormatError, match=r"b\.npz: unknown blend mode 'glow'"):
        Particles.load(tmp_path / "b.npz")


def test_the_exact_path_is_stored_only_when_asked_for(tmp_path):
    """``coarse``: from the preset, an appearance setting; a particle file holds it only when
    false (the files of the default path keep their bytes, and files written before the key
    existed read as the coarse path)."""
    fog = load_preset("fog", {"coarse": "false"})
    assert RenderSettings.from_preset(fog).coarse is False
    assert RenderSettings.from_preset(load_preset("fog")).coarse is True
    assert "coarse" in APPEARANCE_KEYS and "coarse" in APPEARANCE_FIELDS
    exact = empty_particles("camera1", RenderSettings(coarse=False)).save(tmp_path / "e.npz")
    default = empty_particles("camera1", RenderSettings()).save(tmp_path / "d.npz")
    with np.load(exact) as a, np.load(default) as b:
        assert "coarse" in json.loads(str(a["scalars"]))
        assert "coarse" not in json.loads(str(b["scalars"]))
    assert Particles.load(exact).settings.coarse is False
    assert Particles.load(default).settings.coarse is True
