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
from weathergen.datasets.geometry_check import flow_errors, sample_indices, summarize
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


def test_without_ground_truth_flow_there_are_no_figures(tmp_path, demo_root):
    frames, _ = demo_sequence("street")
    root = write_fake_custom(tmp_path / "walk", frames)
    assert check_dataset(open_dataset("custom", root), geometry=True)[0].geometry is None
    res = run_cli("check", "--dataset", "custom", "--root", str(root), "--geometry")
    assert res.exit_code == 0 and "walk: geometry: no ground-truth flow to compare with" in res.output


def test_spring_extrinsics_read_the_wrong_way_round_show(tmp_path, demo_root):
    from fake_datasets import write_fake_spring

    frames, pairs = demo_sequence("street")
    root = write_fake_spring(tmp_path / "spring", frames[:2], pairs=pairs[:1])
    right = check_dataset(open_dataset("spring", root), geometry=True)[0].geometry
    wrong = check_dataset(open_dataset("spring", root, extrinsics="camera-to-world"), geometry=True)[0].geometry
    assert right.median_px < 1e-3 and right.within_1px == 1.0
    assert wrong.median_px > 5 and wrong.within_1px < 0.05
