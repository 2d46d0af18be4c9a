"""`weathergen render --preset fog`: the coarse path by default, the exact path one `--set` away."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from weathergen.cli.main import _register, cli
from weathergen.datasets import open_dataset
from weathergen.engine import Particles, render_pair
from weathergen.io.images import read_image

#: The street scene's first pair; fog billboards of 201 px (still drawn on the 8x coarser grid by
#: default) keep the exact path quick.
FOG = ("--preset", "fog", "--scenes", "street", "--frames-per-scene", "1", "--set", "size=201")
FRAME = "training/fog_clean/street_0001/frame_0001.png"

pytestmark = pytest.mark.slow


def run(*args):
    _register()
    return CliRunner().invoke(cli, [str(a) for a in args])


def png(path) -> np.ndarray:
    """An 8-bit frame as integers."""
    return np.round(read_image(path) * 255).astype(int)


def test_the_exact_path_is_one_set_away(tmp_path, demo_root):
    coarse, exact = tmp_path / "coarse", tmp_path / "exact"
    res = run("render", "--out", coarse, *FOG)
    assert res.exit_code == 0, res.output
    res = run("render", "--out", exact, *FOG, "--set", "coarse=false")
    assert res.exit_code == 0, res.output
    assert json.loads((exact / "manifest.json").read_text())["preset"]["coarse"] is False
    # the same particles, drawn exactly: the library's exact render of the stored record
    stored = Particles.load(exact / "training/particles/street_0001/frame_0001.npz")
    assert stored.settings.coarse is False
    ds = open_dataset("demo", scenes=["street"])
    pair = ds.load(ds.pairs()[0])
    want = render_pair(pair, stored, coarse_side=None).image1[0]
    want = (want.permute(1, 2, 0).numpy() * 255 + 0.5).astype(int)
    got = png(exact / FRAME)
    assert np.array_equal(got, want)
    # the default path draws the same particles on the coarse grid, within the documented bound
    fast = png(coarse / FRAME)
    assert not np.array_equal(fast, got)
    diff = np.abs(fast - got)
    assert np.quantile(diff, 0.99) <= 10 and diff.mean() <= 1
    assert np.abs(got - (pair.image1.permute(1, 2, 0).numpy() * 255 + 0.5)
                  .astype(int)).mean() > 5                                  # fog is there
    # the switch is an appearance setting: stored particles re-render either way
    again = tmp_path / "again"
    res = run("render", "--out", again, "--particles", coarse, "--set", "coarse=false",
              *FOG[2:6])
    assert res.exit_code == 0, res.output
    assert np.array_equal(png(again / FRAME), got)
    assert torch.equal(Particles.load(again / "training/particles/street_0001/frame_0001.npz")
                       .transparency, stored.transparency)
