"""Particle records (.npz storage) and template libraries."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from engine_scenes import plane_pair
from weathergen.engine import (Particles, generate_templates, load_preset, load_templates,
                               render_pair, sample_particles)
from weathergen.errors import ConfigError, FormatError


@pytest.fixture(scope="module")
def snow_pair_and_particles():
    pair = plane_pair(48, 64, near_block=True)
    # rain's full 3000 particles (a Sintel frame's) on a small frame: the storage size of a record
    return pair, sample_particles(pair, load_preset("rain", {"scale_count": False}), seed=11)


def test_save_load_round_trip_renders_identically(tmp_path, snow_pair_and_particles):
    pair, parts = snow_pair_and_particles
    path = parts.save(tmp_path / "pair.npz")
    again = Particles.load(path)
    for name in ("position", "motion", "offset1", "offset2", "color", "transparency", "template",
                 "rotation", "scale", "defocus"):
        assert torch.equal(getattr(parts, name), getattr(again, name)), name
    assert again.metadata() == parts.metadata()
    a, b = render_pair(pair, parts), render_pair(pair, again)
    assert torch.equal(a.image1, b.image1) and torch.equal(a.image2, b.image2)


def test_storage_is_small_and_plain_numpy(tmp_path, snow_pair_and_particles):
    _, parts = snow_pair_and_particles
    assert parts.count == 3000
    # after an attack the offsets are no longer zero: still well under 200 kB
    gen = torch.Generator().manual_seed(0)
    attacked = parts.replace(offset1=0.01 * torch.randn(3000, 3, generator=gen),
                             offset2=0.01 * torch.randn(3000, 3, generator=gen))
    for rec, name in ((parts, "sampled.npz"), (attacked, "attacked.npz")):
        path = rec.save(tmp_path / name)
        assert path.stat().st_size < 200_000, path.stat().st_size
    with np.load(tmp_path / "sampled.npz", allow_pickle=False) as data:
        assert int(data["format_version"]) == 5
        assert data["position"].dtype == np.uint16 and data["position"].shape == (3000, 3)
        assert data["position_grid"].dtype == np.float64 and data["position_grid"].shape == (2, 3)
        # three 10-bit motion codes per particle in one uint32, decoded by shifts
        words = data["motion"]
        assert words.dtype == np.uint32 and words.shape == (3000,)
        codes = np.stack([(words >> 20) & 1023, (words >> 10) & 1023, words & 1023], -1)
        grid = data["motion_grid"]
        np.testing.assert_array_equal((grid[0] + codes * grid[1]).astype(np.float32),
                                      parts.motion.numpy())
        # the 0-d entries: one JSON entry, name -> [value, dtype]
        scalars = json.loads(str(data["scalars"]))
        assert scalars["frame"] == ["world", "<U5"] and scalars["blur_samples"][0] == 20


@pytest.mark.parametrize("name", ["snow", "rain", "sparks"])
def test_metadata_of_3000_particles_stays_under_60_kB(tmp_path, name):
    """Positions and motions on 15- and 10-bit grids, colours and rotations in 8 bits."""
    pair = plane_pair(436, 1024, depth=6.0, near_block=True)
    parts = sample_particles(pair, load_preset(name), seed=3)
    assert parts.count == 3000
    assert parts.save(tmp_path / "p.npz").stat().st_size <= 60_000
    q = parts.quantized()                                  # sampling already quantized: a no-op
    for field in ("position", "motion", "color", "rotation", "scale", "transparency"):
        assert torch.equal(getattr(q, field), getattr(parts, field)), field
    # the grid really is fine: 15 bits over the sampled positions' extent
    span = parts.position.max(0).values - parts.position.min(0).values
    steps = torch.diff(torch.unique(parts.position[:, 0]))
    assert float(steps.min()) >= float(span[0]) / 32767 * 0.99


def test_version_1_files_are_still_read(tmp_path, snow_pair_and_particles):
    pair, parts = snow_pair_and_particles
    v1 = {"format_version": np.array(1, np.int32)}
    for name, dtype in (("position", np.float32), ("motion", np.float32),
                        ("offset1", np.float16), ("offset2", np.float16), ("color", np.float16),
                        ("transparency", np.float16), ("template", np.uint16),
                        ("rotation", np.float16), ("scale", np.float32), ("defocus", np.uint8)):
        v1[name] = getattr(parts, name).numpy().astype(dtype)
    v1["frame"] = np.array(parts.frame)
    v1.update(parts.settings.to_arrays())
    np.savez(tmp_path / "v1.npz", **v1)
    again = Particles.load(tmp_path / "v1.npz")
    assert torch.equal(again.position, parts.position) and torch.equal(again.motion, parts.motion)
    torch.testing.assert_close(again.color, parts.color, atol=1e-3, rtol=0)


def _as_version_3(arrays: dict) -> dict:
    """A version 5 record's entries in version 3's layout (motion codes (N, 3) uint16; numpy's
    own .npz, one entry per 0-d value), as earlier releases wrote it."""
    old = dict(arrays, format_version=np.array(3, np.int32))
    w = arrays["motion"].astype(np.int64)
    old["motion"] = np.stack([(w >> 20) & 1023, (w >> 10) & 1023, w & 1023], -1).astype(np.uint16)
    return old


def test_version_3_files_are_still_read(tmp_path, snow_pair_and_particles):
    pair, parts = snow_pair_and_particles
    np.savez_compressed(tmp_path / "v3.npz", **_as_version_3(parts.to_numpy()))
    again = Particles.load(tmp_path / "v3.npz")
    for name in ("position", "motion", "offset1", "color", "transparency", "template", "rotation",
                 "scale", "defocus"):
        assert torch.equal(getattr(again, name), getattr(parts, name)), name
    assert again.metadata() == parts.metadata()
    assert torch.equal(render_pair(pair, again).image1, render_pair(pair, parts).image1)


def test_saving_quantizes_and_quantized_records_render_like_the_file(tmp_path):
    pair = plane_pair(32, 40)
    parts = sample_particles(pair, load_preset("snow", {"count": 200}), seed=0)
    nudged = parts.replace(offset1=torch.full_like(parts.offset1, 0.0123456789))
    again = Particles.load(nudged.save(tmp_path / "p.npz"))
    q = nudged.quantized()
    assert torch.equal(again.offset1, q.offset1) and not torch.equal(q.offset1, nudged.offset1)
    assert torch.equal(render_pair(pair, q).image1, render_pair(pair, again).image1)


def test_load_errors(tmp_path, snow_pair_and_particles):
    _, parts = snow_pair_and_particles
    with pytest.raises(FormatError, match="does not exist"):
        Particles.load(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="junk.npz"):
        Particles.load(junk)
    arrays = parts.to_numpy()
    arrays["format_version"] = np.array(99)
    np.savez(tmp_path / "future.npz", **arrays)
    with pytest.raises(FormatError, match="version 99"):
        Particles.load(tmp_path / "future.npz")
    arrays = parts.to_numpy()
    arrays["color"] = arrays["color"][:10]
    np.savez(tmp_path / "short.npz", **arrays)
    with pytest.raises(FormatError, match="'color'"):
        Particles.load(tmp_path / "short.npz")


# -- templates -----------------------------------------------------------------------------

@pytest.mark.parametrize("kind,count,res", [("flakes", 8, 80), ("dust", 6, 128), ("haze", 6, 128)])
def test_builtin_templates_are_shipped_and_regenerable(kind, count, res):
    lib = load_templates(kind)
    assert (lib.count, lib.resolution) == (count, res)
    fresh = np.stack(generate_templates(kind))
    shipped = lib.alphas.numpy()
    assert np.abs(np.round(fresh * 255) / 255 - shipped).max() < 1e-6
    assert float(lib.alphas.amax(dim=(1, 2)).min()) == 1.0


def test_user_template_folder(tmp_path):
    import cv2
    (tmp_path / "a.png").write_bytes(cv2.imencode(".png", np.full((9, 9), 200, np.uint8))[1])
    (tmp_path / "b.png").write_bytes(cv2.imencode(".png", np.full((5, 7), 255, np.uint8))[1])
    lib = load_templates(str(tmp_path))
    assert lib.count == 2 and lib.resolution == 9
    assert float(lib.alphas[1, 4, 4]) == 1.0 and float(lib.alphas[1, 0, 4]) == 0.0  # centred
    pair = plane_pair(32, 40)
    preset = load_preset("snow", {"count": 30, "templates": str(tmp_path)})
    parts = sample_particles(pair, preset, seed=0)
    assert int(parts.template.max()) <= 1
    assert float(render_pair(pair, parts).opacity1.sum()) > 0


def test_template_folder_errors(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ConfigError, match="holds no PNG"):
        load_templates(str(empty))
    with pytest.raises(ConfigError, match="does not exist"):
        load_templates(str(tmp_path / "nowhere"))
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "notes.txt").write_text("hello")
    with pytest.raises(FormatError, match="notes.txt"):
        load_templates(str(bad))
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "flake.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(FormatError, match="flake.png"):
        load_templates(str(broken))
