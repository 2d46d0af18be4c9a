"""Depth you can trust: provenance classes, the sky estimate, completion against exact depth, and
the fog's look on completed depth (weathergen/datasets/depth.py, scripts/depth_completion.py)."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from run_helpers import script_module
from weathergen.datasets.depth import (complete_depth, estimate_sky, extend_upward, lidar_scan,
                                       provenance_shares)
from weathergen.framepair import COMPLETED, MEASURED, SKY, UNKNOWN

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "depth_completion.py"
FAR = 1000.0


@pytest.fixture(scope="module")
def measure():
    with script_module(SCRIPT) as module:
        yield module


def textured(h: int, w: int, seed: int = 0, level: float = 0.4) -> np.ndarray:
    """A textured grey-brown image (strong gradients everywhere: nothing looks like sky)."""
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 0.7)
    return np.clip(level + 0.3 * (noise[..., None] - 0.5) * np.array([1.0, 0.9, 0.7]), 0, 1
                   ).astype(np.float32)


def plane_depth(h: int, w: int) -> np.ndarray:
    """A tilted plane's camera-z depth (inverse depth affine in the pixel), 4 to 10 m."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    return (1.0 / (0.1 + 0.1 * ys / h + 0.05 * xs / w)).astype(np.float32)


def test_a_plane_with_holes_is_measured_around_and_completed_inside():
    h, w = 140, 180
    exact, image = plane_depth(h, w), textured(h, w)
    measured = np.ones((h, w), bool)
    measured[30:110, 40:160] = False                # a large hole (beyond 24 px inside)
    measured[10:13, 10:15] = False                  # a small one
    depth, prov = complete_depth(exact, measured, image, far_depth=FAR)
    assert prov.dtype == np.uint8 and (prov[measured] == MEASURED).all()
    assert (prov[~measured] == COMPLETED).all()     # no sky: the hole is walled in, textured
    np.testing.assert_array_equal(depth[measured], exact[measured])
    rel = np.abs(depth - exact) / exact
    gap = cv2.distanceTransform((~measured).astype(np.uint8), cv2.DIST_L2, 5)
    near, beyond = rel[~measured & (gap <= 24)], rel[gap > 24]
    assert np.median(near) < 0.04 and np.median(beyond) < 0.06, (np.median(near), np.median(beyond))
    assert rel.max() < 0.15 and rel[10:13, 10:15].max() < 0.01
    shares = provenance_shares(prov)
    assert shares["completed"] == pytest.approx((~measured).mean(), abs=1e-4)
    assert shares["measured"] + shares["completed"] == pytest.approx(1.0)
    assert provenance_shares(None)["measured"] == 1.0


def test_without_filling_the_unmeasured_pixels_are_unknown_at_the_far_depth():
    h, w = 60, 80
    exact, image = plane_depth(h, w), textured(h, w)
    measured = np.ones((h, w), bool)
    measured[20:30, 20:30] = False
    sky = np.zeros((h, w), bool)
    sky[:5] = True
    depth, prov = complete_depth(exact, measured & ~sky, image, far_depth=FAR, max_gap_px=0,
                                 sky=sky)
    assert (prov[20:30, 20:30] == UNKNOWN).all() and (depth[20:30, 20:30] == FAR).all()
    assert (prov[:5] == SKY).all() and (depth[:5] == FAR).all()


def test_the_lidar_pattern_has_beams_and_nothing_above_the_top_one():
    k = np.array([[300.0, 0, 191.5], [0, 300.0, 87.5], [0, 0, 1]])
    scan = lidar_scan((176, 384), k, seed=3)
    rows = np.nonzero(scan.any(axis=1))[0]
    top = int(np.rint(87.5 - 300 * np.tan(np.deg2rad(2.0))))
    assert rows.min() == top and 30 < len(rows) <= 64
    assert 0.05 < scan[top:].mean() < 0.15            # sparse, as a scanner's raw returns
    assert (lidar_scan((176, 384), k, seed=3) == scan).all()


def test_the_upward_extension_stops_at_the_sky():
    known = np.zeros((6, 3), bool)
    known[4] = True
    sky = np.zeros((6, 3), bool)
    sky[2, 1] = True                                 # sky cuts column 1 at row 2
    up = extend_upward(np.ones((6, 3), np.float32), known, sky)
    assert up[:4, 0].all() and up[:4, 2].all()
    assert up[3, 1] and not up[2, 1] and not up[:2, 1].any()


def test_the_sky_estimate_takes_the_smooth_bright_top_and_nothing_measured_or_textured():
    h, w = 80, 120
    image = textured(h, w, level=0.35)
    rows = np.linspace(0, 1, 30, dtype=np.float32)[:, None, None]
    image[:30] = np.array([0.6, 0.72, 0.9], np.float32) * (1 - rows) + 0.9 * rows    # the sky
    stripes = np.isin(np.arange(20) % 4, (0, 3))                 # dark at both of its edges
    image[:50, 50:70] = 0.8 - 0.4 * stripes[None, :, None]       # a bright striped pole
    image[40:55, 90:110] = np.array([0.7, 0.8, 0.95])            # smooth and bright, but low
    measured = np.zeros((h, w), bool)
    measured[30::3, ::3] = True
    measured[20::3, 50:70:3] = True                              # the pole is measured higher up
    sky = estimate_sky(image, measured)
    truth = np.zeros((h, w), bool)
    truth[:30] = True
    truth[:, 50:70] = False
    assert (sky & ~truth).sum() == 0                             # nothing but sky
    assert sky[truth].mean() > 0.95
    assert not sky[40:55, 90:110].any()


def test_lidar_depth_of_the_demo_street_is_completed_within_bounds_and_never_in_the_sky(measure):
    frames = measure.lidar_frames(measure.demo_pairs(scenes=("street",), frames_per_scene=1))
    figures = measure.measure(frames)
    assert figures["near"]["median"] < 0.01 and figures["near"]["p90"] < 0.05, figures
    assert figures["beyond"]["median"] < 0.03 and figures["beyond"]["p90"] < 0.5, figures
    assert figures["sky_recall"] > 0.98 and figures["sky_precision"] > 0.95, figures
    sky_pixels = sum(int(f[2].sum()) for f in frames)
    assert figures["completed_in_sky"] < 0.005 * sky_pixels
    # with the sky known (a user's mask) not one completed pixel falls in it
    for image, exact, sky, measured in frames:
        depth, prov = complete_depth(exact, measured, image, far_depth=FAR, sky=sky)
        assert (prov[sky] == SKY).all() and (depth[sky] == FAR).all()
        assert not ((prov == SKY) & ~sky).any() and (prov[~sky & ~measured] == COMPLETED).all()


def test_fog_follows_the_image_not_the_holes_of_the_depth(measure):
    """Fog-moderate on the demo street with a sky: from LiDAR-like depth and from depth with holes
    punched in it, the fog's opacity has (almost) no edge where the image has none once the
    depth is completed, and the white above the top beam is the sky (before: whole walls)."""
    out = measure.fog_comparison()
    exact = out["exact"]
    for name in ("lidar", "holes"):
        before, after = out[f"{name} before"], out[f"{name} after"]
        assert after["edges"] < 0.0015 and after["edges"] < before["edges"] / 4, out
        assert abs(after["white_above"] - after["sky_above"]) < 0.03, out
    assert out["lidar before"]["white_above"] > 2 * exact["sky_above"]      # what it was
    assert abs(exact["white_above"] - exact["sky_above"]) < 0.01


def test_the_sky_gets_the_far_depth_and_the_full_airlight(measure):
    pair = measure.demo_pairs(scenes=("street",), frames_per_scene=1)[0]
    image, exact, sky = measure.street_with_sky(pair)
    scan = lidar_scan(exact.shape, pair.intrinsics.numpy(), seed=1) & ~sky
    depth, prov = complete_depth(exact, scan, image, far_depth=FAR, sky=sky)
    opacity = measure.fog_opacity(pair, image, depth)
    assert (depth[prov == SKY] == FAR).all()
    assert opacity[prov == SKY].min() > 0.95                # the airlight, all of it
    assert np.quantile(opacity[prov == COMPLETED], 0.99) < 0.5


def test_check_shows_the_shares_and_a_render_writes_the_provenance_and_says_what_it_is(
        tmp_path, demo_root):
    import json

    from click.testing import CliRunner

    from fake_datasets import demo_sequence, write_fake_custom
    from weathergen.cli.main import _register, cli
    from weathergen.io.images import read_raw

    _register()
    frames, _ = demo_sequence("street")
    root = write_fake_custom(tmp_path / "s", frames[:2], missing=(0, 60))    # rows 0-59 of frame 0
    res = CliRunner().invoke(cli, ["check", "--dataset", "custom", "--root", str(root)])
    assert res.exit_code == 0, res.output
    line = next(x for x in res.output.splitlines() if "depth frame 1:" in x)
    shares = [float(v) for v in re.findall(r"(\d+\.\d)%", line)]
    assert len(shares) == 8 and abs(sum(shares[:4]) - 100) < 0.3 and shares[4] == 100.0, line
    assert shares[0] == pytest.approx(100 * (1 - 60 / 176), abs=0.1)      # measured
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["render", "--dataset", "custom", "--root", str(root), "--preset",
                                   "fog-light", "--fill-gaps", "0", "--out", str(out)])
    assert res.exit_code == 0, res.output
    said = res.output.replace("\n", " ")
    assert "--fill-gaps 0: no depth is completed; pixels without a measurement that are not sky " \
           "stay unknown at the far depth (1000)" in said
    assert "in 1 pair more than 50% of a frame's depth is completed or more than 2% unknown" in said
    assert "the weather there follows the far depth where it is unknown" in said   # not "estimated"
    written = read_raw(out / "training" / "depth_provenance" / "s_0000" / "frame_0000.png")
    assert written.dtype == np.uint8 and set(np.unique(written)) <= {MEASURED, SKY, UNKNOWN}
    assert (written[60:] == MEASURED).all() and (written[:60] != MEASURED).all()
    manifest = json.loads((out / "manifest.json").read_text())
    facts = next(iter(manifest["pairs"].values()))["input"]["depth_provenance"]
    assert facts[0]["measured"] == pytest.approx(1 - 60 / 176, abs=1e-3)
    assert facts[0]["unknown"] + facts[0]["sky"] == pytest.approx(60 / 176, abs=1e-3)


def test_an_attack_run_records_the_shares_and_says_when_depth_is_mostly_estimated(tmp_path,
                                                                                   demo_root):
    import json

    from fake_datasets import demo_sequence, write_fake_custom
    from weathergen.attack import AttackJob, plan_attack, run_attack
    from weathergen.datasets import open_dataset

    frames, _ = demo_sequence("street")
    root = write_fake_custom(tmp_path / "s", frames[:2], missing=(0, 60))
    plan = plan_attack(None, "snow", {"count": "20"}, steps=1)
    notes = []
    run_attack(AttackJob(dataset=open_dataset("custom", root, max_gap_px=0), out=tmp_path / "a",
                         model="raft-small", checkpoint=None, preset=plan.preset,
                         preset_name=plan.preset_name, settings=plan.settings),
               on_note=notes.append)
    assert sum("of a frame's depth is completed or more than 2% unknown" in n for n in notes) == 1
    assert sum(n.startswith("--fill-gaps 0: no depth is completed") for n in notes) == 1
    entry = next(iter(json.loads((tmp_path / "a" / "manifest.json").read_text())["pairs"].values()))
    assert entry["depth_provenance"][0]["measured"] == pytest.approx(1 - 60 / 176, abs=1e-3)
