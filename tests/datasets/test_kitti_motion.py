"""KITTI camera motion by OpenCV's PnP RANSAC + LM: moving objects, thresholds, feature matching."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from fake_datasets import KITTI_BASELINE, demo_sequence, rigid, write_fake_kitti, write_moving_kitti
from weathergen.datasets import open_dataset
from weathergen.datasets.camera_motion import (FitSettings, backproject_pixels, check_fit,
                                               fit_motion_pnp, reprojection_errors)
from weathergen.errors import DatasetError
from weathergen.io.kitti_formats import write_disparity_png

#: The ego-motion of the synthetic pairs: 1.5° yaw, 0.4° pitch, 0.8 scene units forward.
TRUTH = rigid(1.5, 0.4, (0.05, -0.02, -0.8))
#: Recovered within these (on exact data the errors are ~1e-4° and ~1e-5 units).
ROT_TOL_DEG, TRANS_TOL = 0.02, 0.005


def motion_errors(estimate, truth):
    estimate = np.asarray(estimate, np.float64)
    r = estimate[:3, :3] @ truth[:3, :3].T
    rot = float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))
    return rot, float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))


@pytest.fixture(scope="module")
def street(demo_root):
    return demo_sequence("street")[1]


def load_one(root, **options):
    ds = open_dataset("kitti", root, **options)
    return ds.load(ds.pairs()[0])


# -- the fit on its own --------------------------------------------------------------------------
def test_reprojection_errors_by_hand():
    k = np.array([[100.0, 0, 50], [0, 100, 40], [0, 0, 1]])
    motion = rigid(0, 0, (0.5, 0, 1.0))            # x moves 0.5, z moves 1 further
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -3.0]])
    # (0, 0, 1) -> (0.5, 0, 2): pixel (50 + 100 * 0.25, 40) = (75, 40); observed at (78, 44)
    err = reprojection_errors(motion, points, np.array([[78.0, 44.0], [0.0, 0.0]]), k)
    assert err[0] == pytest.approx(5.0) and err[1] == np.inf     # the second is behind camera 2


def test_fit_ignores_a_30_percent_rigid_object_and_is_deterministic():
    rng = np.random.default_rng(3)
    k = np.array([[720.0, 0, 620], [0, 720, 190], [0, 0, 1]])
    n = 3000
    pts = np.c_[rng.uniform(-15, 15, n), rng.uniform(-2.5, 1.5, n), rng.uniform(4, 60, n)]
    moving = np.arange(n) < 0.3 * n
    obj = rigid(4.0, 0.0, (1.0, 0.0, -0.5))
    own = np.where(moving[:, None], pts @ obj[:3, :3].T + obj[:3, 3], pts)
    moved = own @ TRUTH[:3, :3].T + TRUTH[:3, 3]
    pix = moved[:, :2] / moved[:, 2:] * [k[0, 0], k[1, 1]] + k[:2, 2]
    pix += rng.normal(0, 0.3, pix.shape)
    fit = fit_motion_pnp(pts, pix, k)
    rot, trans = motion_errors(fit.cam2_from_cam1, TRUTH)
    assert rot < 0.02 and trans < 0.01
    assert not fit.inliers[moving].any() and fit.inliers[~moving].mean() > 0.99
    assert fit.inlier_fraction == pytest.approx(0.7, abs=0.01)
    assert 0.2 < fit.rms_px < 0.5                           # the noise: 0.3 px per axis
    again = fit_motion_pnp(pts, pix, k)
    np.testing.assert_array_equal(again.cam2_from_cam1, fit.cam2_from_cam1)
    summary = fit.summary()
    assert summary["rotation_deg"] == pytest.approx(np.degrees(np.arccos((np.trace(TRUTH[:3, :3]) - 1) / 2)), abs=0.02)
    assert summary["translation"] == pytest.approx(list(TRUTH[:3, 3]), abs=0.01)
    assert check_fit(fit, FitSettings()) is None
    refused = check_fit(fit, FitSettings(min_inlier_fraction=0.9))
    assert refused.startswith("only 70.0% of 3000 correspondences agree with one camera motion "
                              "within 2 px (at least 90% required); best motion t=(+0.050, -0.020, -0.800)")


def test_backproject_pixels_inverts_projection():
    k = np.array([[300.0, 2.0, 190], [0, 310, 90], [0, 0, 1]])
    pts = np.array([[1.0, -0.5, 4.0], [-2.0, 0.3, 9.0]])
    pix = reprojection_errors(np.eye(4), pts, np.zeros((2, 2)), k)  # distance to (0, 0)
    u = k[0, 0] * pts[:, 0] / pts[:, 2] + k[0, 1] * pts[:, 1] / pts[:, 2] + k[0, 2]
    v = k[1, 1] * pts[:, 1] / pts[:, 2] + k[1, 2]
    assert pix == pytest.approx(np.hypot(u, v))
    np.testing.assert_allclose(backproject_pixels(np.c_[u, v], pts[:, 2], k), pts)


# -- the reader ----------------------------------------------------------------------------------
@pytest.mark.parametrize("without_objects", ["", "option", "no file"])
def test_ego_motion_with_30_percent_moving_pixels(tmp_path, street, without_objects):
    s, moving = write_moving_kitti(tmp_path, street[0], TRUTH, moving_fraction=0.3)
    options = {}
    if without_objects == "option":
        options["use_object_map"] = False
    elif without_objects == "no file":
        shutil.rmtree(s / "obj_map")
    pair = load_one(tmp_path, **options)
    rot, trans = motion_errors(pair.cam2_from_cam1, TRUTH)
    assert rot < ROT_TOL_DEG and trans < TRANS_TOL
    fit = pair.meta["camera_motion"]
    assert fit["translation"] == pytest.approx(list(TRUTH[:3, 3]), abs=TRANS_TOL)
    points = fit["points"]
    if without_objects:
        # every static point agrees, no moving one does
        assert fit["inliers"] == points - moving.sum()
        assert 0.3 <= moving.sum() / points < 0.4
    else:
        assert fit["inlier_fraction"] == 1.0


def test_noisy_measurements_still_give_the_motion(tmp_path, street):
    write_moving_kitti(tmp_path, street[0], TRUTH, noise_px=0.3, seed=1)
    pair = load_one(tmp_path, use_object_map=False)
    rot, trans = motion_errors(pair.cam2_from_cam1, TRUTH)
    assert rot < 0.05 and trans < 0.01
    assert 0.3 < pair.meta["camera_motion"]["rms_px"] < 0.8


def test_an_unreachable_inlier_threshold_is_refused_with_the_figures(tmp_path, street):
    write_moving_kitti(tmp_path, street[0], TRUTH)
    with pytest.raises(DatasetError) as info:
        load_one(tmp_path, use_object_map=False, fit_min_inlier_fraction=0.9)
    message = str(info.value)
    assert "flow_occ/000000_10.png: camera motion of pair 000000 (frames 10-11) is not trusted: only 6" in message
    assert "correspondences agree with one camera motion within 2 px (at least 90% required); " \
           "best motion t=(+0.050, -0.020, -0.800), rotation 1.55°" in message
    assert "inlier RMS 0.01 px" in message
    # an unreachable reprojection error, likewise
    with pytest.raises(DatasetError, match=r"inliers' reprojection error is 0\.01 px RMS, above the "
                                           r"0\.001 px allowed; motion t=\(\+0\.050, -0\.020, -0\.800\)"):
        load_one(tmp_path, fit_max_rms_px=0.001)


def test_features_give_the_motion_where_no_flow_exists(tmp_path, street):
    # the testing split with disparities of one's own for both frames, and no flow
    truth = street[1]
    s = write_fake_kitti(tmp_path, truth, split="testing")
    fb = truth.intrinsics[0, 0].item() * KITTI_BASELINE
    write_disparity_png(s / "disp_occ_0" / "000000_10.png", fb / truth.depth1[0].numpy())
    write_disparity_png(s / "disp_occ_0" / "000000_11.png", fb / truth.depth2[0].numpy())
    ds = open_dataset("kitti", tmp_path, split="testing", fit_min_points=30)
    pair = ds.load(ds.pairs()[0])
    rot, trans = motion_errors(pair.cam2_from_cam1, truth.cam2_from_cam1.numpy())
    assert rot < 0.1 and trans < 0.02
    fit = pair.meta["camera_motion"]
    assert fit["correspondences"] == "features" and fit["points"] >= 30
    assert pair.flow is None
    torch_depth2 = pair.depth2[0].numpy()
    np.testing.assert_allclose(torch_depth2, truth.depth2[0].numpy(), rtol=5e-3)
    # too few matches for the asked minimum: refused, naming the pair
    with pytest.raises(DatasetError, match=r"camera motion of pair 000000 \(frames 10-11\): only \d+ "
                                           r"matched features \(no flow_occ file\)"):
        load_one(tmp_path, split="testing", fit_min_points=5000)


# -- the command line ----------------------------------------------------------------------------
def run_cli(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, args)


def test_check_shows_the_motion_and_takes_the_fit_options(tmp_path, street):
    write_moving_kitti(tmp_path, street[0], TRUTH)
    res = run_cli(["check", "--dataset", "kitti", "--root", str(tmp_path), "--no-object-map"])
    assert res.exit_code == 0, res.output
    assert re.search(r"000000 frame 10: camera motion t=\(\+0\.050, -0\.020, -0\.800\), rotation 1\.55°, "
                     r"6\d% of \d+ points within 2 px, RMS 0\.01 px", res.output), res.output
    res = run_cli(["check", "--dataset", "kitti", "--root", str(tmp_path), "--no-object-map",
                   "--fit-min-inliers", "0.9"])
    assert res.exit_code == 1
    assert "(at least 90% required)" in res.output
    res = run_cli(["check", "--dataset", "kitti", "--root", str(tmp_path), "--fit-threshold", "0"])
    assert res.exit_code == 2 and "fit threshold must be a positive number of pixels, got 0" in res.output


def test_manifest_records_the_motion(tmp_path, street):
    write_moving_kitti(tmp_path / "kitti", street[0], TRUTH)
    out = tmp_path / "out"
    res = run_cli(["render", "--dataset", "kitti", "--root", str(tmp_path / "kitti"), "--out", str(out),
                   "--set", "count=50", "--fit-threshold", "1.5"])
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "manifest.json").read_text())
    fit = manifest["pairs"]["kitti:training:000000:10"]["input"]["camera_motion"]
    assert fit["translation"] == pytest.approx(list(TRUTH[:3, 3]), abs=TRANS_TOL)
    assert fit["rotation_deg"] == pytest.approx(1.55, abs=0.01)
    assert fit["inlier_fraction"] == 1.0 and fit["rms_px"] < 0.05 and fit["threshold_px"] == 1.5
    assert manifest["input"]["fit_threshold_px"] == 1.5
