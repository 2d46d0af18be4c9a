"""Particle-metadata files: as small as docs/render.md says, and the earlier formats still read."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from engine_scenes import plane_pair
from weathergen.cli.main import cli
from weathergen.engine import Particles, load_preset, sample_particles
from weathergen.framepair import PairId
from weathergen.io.images import read_image
from weathergen.io.npz import SCALARS, read_npz
from weathergen.outputs import PairOutput, pair_metadata, read_metadata, write_metadata


@pytest.mark.parametrize("name", ["snow", "rain", "sparks"])
def test_a_render_metadata_file_of_3000_particles_is_under_60_kB(tmp_path, name):
    """The bound of docs/render.md, for the whole file a render writes (record, identity, file
    list) on a Sintel-size frame; sparks (motion and colour per particle) is the largest."""
    pair = plane_pair(436, 1024, depth=6.0, near_block=True)
    preset = load_preset(name)
    parts = sample_particles(pair, preset, seed=3)
    assert parts.count == 3000
    pair_id = PairId("sintel", "training", "ambush_2", 1)
    out = PairOutput.of(tmp_path, pair_id, f"{name}_clean", "both", geometry=True)
    meta = pair_metadata(parts, pair_id, 1234567890123, preset.to_dict(), name)
    meta["visible1"], meta["visible2"] = np.array(2950, np.int64), np.array(2940, np.int64)
    meta["files"] = np.array(json.dumps([str(p.relative_to(tmp_path))
                                         for p in out.files(with_flow=True)]))
    size = write_metadata(out.metadata, meta).stat().st_size
    assert size < 60_000, f"{name}: {size} bytes"
    back = read_metadata(out.metadata)
    assert sorted(back) == sorted(meta)
    for key, value in meta.items():
        np.testing.assert_array_equal(back[key], value, err_msg=key)
        assert back[key].dtype == value.dtype, key


def _as_metadata_version_1(arrays: dict) -> dict:
    """Entries of a current metadata file as release 0.1's first format wrote them: particle
    format 3 (motion codes (N, 3) uint16) and metadata version 1, one entry per 0-d value."""
    old = dict(arrays, metadata_version=np.array(1, np.int32))
    if "optics" not in arrays:
        old["format_version"] = np.array(3, np.int32)
        w = arrays["motion"].astype(np.int64)
        old["motion"] = np.stack([(w >> 20) & 1023, (w >> 10) & 1023, w & 1023],
                                 -1).astype(np.uint16)
    else:
        old["format_version"] = np.array(2, np.int32)
    return old


@pytest.mark.parametrize("preset", ["rain", "snow-light"])
def test_outputs_in_the_earlier_format_re_render_bit_identically(tmp_path, demo_root, preset):
    """A render folder whose metadata files are in the earlier formats (metadata version 1 with
    particle version 3, or 2 for weather fields) is read, and re-renders the same bytes."""
    args = ["--scenes", "street", "--frames-per-scene", "2", "--preset", preset,
            "--set", "count=300" if preset == "rain" else "far=5"]
    src = tmp_path / "src"
    res = CliRunner().invoke(cli, ["render", "--out", str(src), "-q", *args])
    assert res.exit_code == 0, res.output
    files = sorted(src.rglob("particles/*/*.npz"))
    assert len(files) == 2
    for path in files:
        with np.load(path) as data:
            assert SCALARS in data.files and int(data["metadata_version"]) == 2
        current = read_npz(path)
        np.savez_compressed(path, **_as_metadata_version_1(current))
        with np.load(path) as data:
            assert SCALARS not in data.files and "pair_scene" in data.files
        again = read_metadata(path)
        assert Particles.load(path).count == Particles.from_arrays(current, path).count
        assert int(again["metadata_version"]) == 1
    out = tmp_path / "again"
    res = CliRunner().invoke(cli, ["render", "--out", str(out), "--particles", str(src), "-q",
                                   *args[:4]])
    assert res.exit_code == 0, res.output
    frames = sorted(p.relative_to(src) for p in src.rglob("*.png")
                    if "particles" not in p.parts and p.parent.parent.name.endswith("_clean"))
    assert frames
    for rel in frames:
        assert torch.equal(torch.from_numpy(read_image(out / rel)), torch.from_numpy(read_image(src / rel)))
