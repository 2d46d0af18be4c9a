"""What a run records about a paper preset's count on its frames, and outputs written before it."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from weathergen.cli.main import _register, cli
from weathergen.engine import Particles, frame_scaling, load_preset
from weathergen.outputs import read_metadata, stored_frame_scaling, write_metadata

pytestmark = pytest.mark.slow

ONE_PAIR = ("--scenes", "street", "--frames-per-scene", "1")
NPZ = Path("training/particles/street_0001/frame_0001.npz")


def run(*args):
    _register()
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def snow_run(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("frames") / "snow"
    res = run("render", "--out", out, *ONE_PAIR)
    assert res.exit_code == 0, res.output
    return out


def test_the_manifest_and_metadata_record_the_count_and_the_rule(snow_run):
    manifest = json.loads((snow_run / "manifest.json").read_text())
    preset = manifest["preset"]
    assert (preset["count"], preset["size"]) == (3000, 71)
    assert (preset["scale_count"], preset["scale_size"]) == (True, False)
    (entry,) = manifest["pairs"].values()
    assert entry["particles"] == 454            # 3000 x 384 x 176 / (1024 x 436) = 454.13

    arrays = read_metadata(snow_run / NPZ)
    recorded = stored_frame_scaling(arrays)
    assert recorded == frame_scaling(load_preset("snow"), 176, 384).to_dict()
    assert (recorded["count"], recorded["count_rule"], recorded["size"]) == (454, "area", 71)
    assert (recorded["height"], recorded["width"], recorded["reference"]) == (176, 384, [436, 1024])
    assert Particles.load(snow_run / NPZ).count == 454
    res = run("inspect", snow_run / NPZ)
    assert res.exit_code == 0, res.output
    assert "454 particles = 3000 x area 384x176 / 1024x436" in " ".join(res.output.split())


def test_an_explicit_count_is_recorded_as_fixed(tmp_path, demo_root):
    out = tmp_path / "exact"
    res = run("render", "--out", out, *ONE_PAIR, "--set", "count=120")
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert (manifest["preset"]["count"], manifest["preset"]["scale_count"]) == (120, False)
    assert next(iter(manifest["pairs"].values()))["particles"] == 120
    recorded = stored_frame_scaling(read_metadata(out / NPZ))
    assert (recorded["count"], recorded["count_rule"]) == (120, "fixed")


def _as_written_before_frame_scaling(folder: Path) -> None:
    """Rewrite a render folder as the version before the count scaled wrote it: no
    frame_scaling entry, no switches in the recorded presets."""
    for path in folder.rglob("*.npz"):
        arrays = read_metadata(path)
        del arrays["frame_scaling"]
        old = {k: v for k, v in json.loads(str(arrays["preset"])).items()
               if k not in ("scale_count", "scale_size")}
        arrays["preset"] = np.array(json.dumps(old, sort_keys=True))
        write_metadata(path, arrays)
    for path in [folder / "manifest.json", *(folder / "manifest.d").glob("*.json")]:
        data = json.loads(path.read_text())
        for holder in (data, data.get("config", {})):
            for key in ("scale_count", "scale_size"):
                holder.get("preset", {}).pop(key, None)
        path.write_text(json.dumps(data))


def test_outputs_written_before_still_read_and_re_render(tmp_path, demo_root):
    old = tmp_path / "old"
    res = run("render", "--out", old, *ONE_PAIR, "--set", "count=200")
    assert res.exit_code == 0, res.output
    _as_written_before_frame_scaling(old)
    with zipfile.ZipFile(old / NPZ) as z:
        assert "frame_scaling.npy" not in z.namelist()
    arrays = read_metadata(old / NPZ)
    assert stored_frame_scaling(arrays) is None
    assert Particles.load(old / NPZ).count == 200
    res = run("inspect", old / NPZ)
    assert res.exit_code == 0 and "not recorded" in res.output, res.output
    # re-rendering takes the stored particles and their preset as it was (count as given)
    again = tmp_path / "again"
    res = run("render", "--particles", old, "--out", again, *ONE_PAIR, "--set", "blend=alpha")
    assert res.exit_code == 0, res.output
    manifest = json.loads((again / "manifest.json").read_text())
    assert (manifest["preset"]["count"], manifest["preset"]["scale_count"]) == (200, False)
    assert Particles.load(again / NPZ).count == 200
