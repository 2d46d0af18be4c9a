"""The geometry self-check: depth + cameras against the dataset's own ground-truth flow."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from fake_datasets import demo_sequence, write_fake_custom
from weathergen.datasets import open_dataset
from weathergen.datasets.checking import check_dataset
from weathergen.datasets.geometry_check import (flow_errors, photometric_errors, sample_indices, summarize,
                                               summarize_photometric)
from weathergen.framepair import FramePair, PairId


def run_cli(*args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, list(args))


def plane_pair(flow_u: float) -> FramePair:
    """A fronto-parallel plane at depth 2 seen by f = 100 cameras; camera 2 is 0.1 to the right,
    so the static flow is u = -100 * 0.1 / 2 = -5 px everywhere. The given flow is ``flow_u``."""
    h, w = 6, 8
    k = torch.tensor([[100.0, 0, 3.5], [0, 100, 2.5], [0, 0, 1]], dtype=torch.float64)
    motion = torch.eye(4, dtype=torch.float64)
    motion[0, 3] = -0.1                      # points move left in camera 2's frame
    flow = torch.zeros(2, h, w)
    flow[0] = flow_u
    return FramePair(id=PairId("t", "t", "t", 0), image1=torch.zeros(3, h, w), image2=torch.zeros(3, h, w),
                     depth1=torch.full((1, h, w), 2.0), depth2=torch.full((1, h, w), 2.0),
                     intrinsics=k, cam2_from_cam1=motion, flow=flow,
                     flow_valid=torch.ones(1, h, w, dtype=torch.bool))


def test_flow_errors_by_hand():
    exact = flow_errors(plane_pair(-5.0))
    # pixels whose target leaves the frame (the 5 rightmost... leftmost columns) are not compared
    assert exact.size == 6 * 3 and np.abs(exact).max() < 1e-9
    off = flow_errors(plane_pair(-2.0))      # a flow 3 px off lands on other pixels of the plane
    assert off.size == 6 * 6 and np.allclose(off, 3.0)
    stats = summarize([off, exact])
    assert stats.median_px == pytest.approx(3.0) and stats.within_1px == pytest.approx(18 / 54)
    assert stats.pairs == 2 and stats.pixels == 54
    pair = plane_pair(-5.0)
    pair.flow = None
    assert flow_errors(pair) is None and summarize([None]) is None


def test_sample_indices_spread_over_the_scene():
    assert sample_indices(2, 3) == [0, 1]
    assert sample_indices(10, 3) == [0, 4, 9] or sample_indices(10, 3) == [0, 5, 9]
    assert sample_indices(10, 1) == [0]


def test_demo_scene_is_exact_and_a_scaled_depth_stays_exact(demo_root):
    res = run_cli("check", "--geometry")
    assert res.exit_code == 0, res.output
    for scene in ("courtyard", "street"):
        assert re.search(rf"^{scene}: geometry: flow error median 0\.000 px, p90 0\.000 px, 100\.0% "
                         rf"within 1 px \(3 pairs, \d+ pixels\)$", res.output, re.M), res.output
    # depth scale multiplies depth and camera translation: geometry stays consistent
    scenes = check_dataset(open_dataset("demo", depth_scale=3.0, frames_per_scene=1), geometry=True)
    assert all(sc.geometry.p90_px < 1e-3 for sc in scenes)


def test_inverted_extrinsics_show_as_a_large_error(tmp_path, demo_root):
    frames, pairs = demo_sequence("street")
    root = write_fake_custom(tmp_path / "walk", frames, pose="world_from_cam", flows=pairs)
    good = check_dataset(open_dataset("custom", root), geometry=True, geometry_pairs=2)[0].geometry
    assert good.median_px < 1e-3 and good.within_1px == 1.0 and good.pairs == 2
    # the same tree with the pose convention declared the wrong way round
    cams = json.loads((root / "cameras.json").read_text())
    cams["pose"] = "cam_from_world"
    (root / "cameras.json").write_text(json.dumps(cams))
    bad = check_dataset(open_dataset("custom", root), geometry=True, geometry_pairs=2)[0].geometry
    assert bad.median_px > 5 and bad.within_1px < 0.05
    res = run_cli("check", "--dataset", "custom", "--root", str(root), "--geometry")
    assert res.exit_code == 0          # readable; the figures are for the user to judge
    median = re.search(r"^walk: geometry: flow error median (\d+\.\d+) px", res.output, re.M)
    assert median and float(median.group(1)) > 5, res.output


def test_spring_extrinsics_read_the_wrong_way_round_show(tmp_path, demo_root):
    from fake_datasets import write_fake_spring

    frames, pairs = demo_sequence("street")
    root = write_fake_spring(tmp_path / "spring", frames[:2], pairs=pairs[:1])
    right = check_dataset(open_dataset("spring", root), geometry=True)[0].geometry
    wrong = check_dataset(open_dataset("spring", root, extrinsics="camera-to-world"), geometry=True)[0].geometry
    assert right.median_px < 1e-3 and right.within_1px == 1.0
    assert wrong.median_px > 5 and wrong.within_1px < 0.05


def ramp_pair(shift: float) -> FramePair:
    """The plane of :func:`plane_pair` (static flow -5 px) with a grey ramp I1(x) = x / 20, and
    frame 2 as the cameras see it: I2(x) = I1(x + 5). ``shift`` multiplies the camera motion."""
    pair = plane_pair(-5.0)
    pair.flow = pair.flow_valid = None
    h, w = pair.size
    x = torch.arange(w, dtype=torch.float32).expand(3, h, w)
    pair.image1, pair.image2 = x / 20, (x + 5) / 20
    pair.cam2_from_cam1[0, 3] *= shift
    return pair


def test_photometric_errors_by_hand():
    warped, unmoved, motion = photometric_errors(ramp_pair(1.0))
    # frame-1 columns 5..7 land on columns 0..2 of frame 2, which shows them there
    assert warped.size == 6 * 3 and np.abs(warped).max() < 1e-6
    assert np.allclose(unmoved, 0.25) and np.allclose(motion, 5.0)
    wrong = photometric_errors(ramp_pair(-1.0))      # motion the wrong way: columns 0..2 land on 5..7
    assert wrong[0].size == 18 and np.allclose(wrong[0], 0.5) and np.allclose(wrong[2], 5.0)
    good = summarize_photometric([(warped, unmoved, motion)], 48)
    assert good.judged and good.explained and good.coverage == pytest.approx(18 / 48)
    bad = summarize_photometric([wrong], 48)
    assert bad.judged and not bad.explained and bad.error == pytest.approx(0.5)
    still = summarize_photometric([photometric_errors(ramp_pair(0.1))], 48)   # 0.5 px: too little
    assert not still.judged and still.motion_px == pytest.approx(0.5)
    assert summarize_photometric([], 0) is None


def test_check_without_flow_uses_the_frames_and_warns_about_a_wrong_convention(tmp_path):
    frames, _ = demo_sequence("street")
    root = write_fake_custom(tmp_path / "walk", frames)             # no flow/: nothing to compare with
    assert check_dataset(open_dataset("custom", root), geometry=True)[0].geometry is None
    res = run_cli("check", "--dataset", "custom", "--root", str(root), "--geometry")
    assert res.exit_code == 0, res.output
    line = re.search(r"^walk: geometry: no ground-truth flow; photometric check consistent: .*$", res.output, re.M)
    assert line, res.output
    error, unmoved = (float(v) for v in re.search(r"frame 1 by ([\d.]+) .* in place by ([\d.]+)", line[0]).groups())
    assert error < 0.5 * unmoved
    assert "warning" not in res.output
    cams = json.loads((root / "cameras.json").read_text())
    cams["pose"] = "world_from_cam"                                  # declared the wrong way round
    (root / "cameras.json").write_text(json.dumps(cams))
    res = run_cli("check", "--dataset", "custom", "--root", str(root), "--geometry")
    assert res.exit_code == 0, res.output                            # a warning, not an error
    assert "walk: geometry: no ground-truth flow; photometric check NOT consistent" in res.output
    assert "walk: warning: depth and cameras do not explain the frames" in res.output
    scenes = check_dataset(open_dataset("custom", root), geometry=True)
    assert scenes[0].photometric.judged and not scenes[0].photometric.explained
