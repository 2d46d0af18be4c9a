"""KITTI 2015: formats, densified depth, the fitted camera motion and every bad-input path."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from fake_datasets import KITTI_BASELINE, demo_sequence, write_fake_kitti
from weathergen.datasets import open_dataset
from weathergen.datasets.densify import fill_sparse
from weathergen.framepair import COMPLETED, SKY, UNKNOWN
from weathergen.datasets.kitti import forward_warp_disparity
from weathergen.errors import ConfigError, DatasetError, FormatError
from weathergen.geometry import rotation_angle_deg
from weathergen.io.kitti_formats import (read_calibration, read_disparity_png, read_flow_png,
                                         read_object_map, stereo_camera, write_calibration,
                                         write_disparity_png, write_flow_png, write_object_map)


@pytest.fixture(scope="module")
def street(demo_root):
    return demo_sequence("street")[1]


def load_one(root, **options):
    ds = open_dataset("kitti", root, **options)
    refs = ds.pairs()
    assert len(refs) == 1
    return ds.load(refs[0])


def motion_errors(estimate, truth):
    rot = float(rotation_angle_deg(estimate[:3, :3] @ truth[:3, :3].T))
    return rot, float((estimate[:3, 3] - truth[:3, 3]).norm())


# -- formats -------------------------------------------------------------------------------------
def test_disparity_png_round_trip_and_invalid_pixels(tmp_path):
    disp = np.array([[0.0, 1.5, 200.123], [np.nan, 0.001, 63.9]])
    write_disparity_png(tmp_path / "d.png", disp)
    back, valid = read_disparity_png(tmp_path / "d.png")
    np.testing.assert_array_equal(valid, [[False, True, True], [False, True, True]])
    np.testing.assert_allclose(back[valid], [1.5, 51231 / 256, 1 / 256, 16358 / 256], rtol=0, atol=1e-6)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw[0, 1] == 384          # 1.5 * 256


def test_flow_png_channel_order_and_round_trip(tmp_path):
    flow = np.zeros((2, 3, 2))
    flow[0, 1] = (2.5, -1.25)
    valid = np.array([[True, True, False], [True, True, True]])
    write_flow_png(tmp_path / "f.png", flow, valid)
    raw = cv2.imread(str(tmp_path / "f.png"), cv2.IMREAD_UNCHANGED)
    # file order is (u, v, valid), so OpenCV's BGR puts u last
    assert tuple(raw[0, 1]) == (1, 2 ** 15 - 80, 2 ** 15 + 160)
    back, back_valid = read_flow_png(tmp_path / "f.png")
    np.testing.assert_array_equal(back_valid, valid)
    np.testing.assert_allclose(back, flow)


def test_flow_png_refuses_flow_it_cannot_store(tmp_path):
    with pytest.raises(ValueError, match="512"):
        write_flow_png(tmp_path / "f.png", np.full((2, 2, 2), 600.0))


def test_object_map_and_calibration(tmp_path):
    write_object_map(tmp_path / "o.png", np.array([[0, 1], [2, 0]]))
    np.testing.assert_array_equal(read_object_map(tmp_path / "o.png"), [[0, 1], [2, 0]])
    k = np.array([[721.5, 0, 609.6], [0, 721.5, 172.9], [0, 0, 1]])
    write_calibration(tmp_path / "c.txt", k, 0.5327)
    k_back, baseline = stereo_camera(tmp_path / "c.txt")
    np.testing.assert_allclose(k_back, k)
    assert baseline == pytest.approx(0.5327)
    assert "calib_time" not in read_calibration(tmp_path / "c.txt")   # not numeric: skipped


def test_wrong_png_kinds_are_named(tmp_path):
    cv2.imwrite(str(tmp_path / "eight.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(FormatError, match=r"eight\.png: is a uint8 image, expected a 16-bit PNG"):
        read_disparity_png(tmp_path / "eight.png")
    write_disparity_png(tmp_path / "grey.png", np.ones((4, 4)))
    with pytest.raises(FormatError, match=r"grey\.png: has 1 channels, expected 3"):
        read_flow_png(tmp_path / "grey.png")
    (tmp_path / "c.txt").write_text("P_rect_02: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(FormatError, match=r"c\.txt: has no P_rect_03 line"):
        stereo_camera(tmp_path / "c.txt")


# -- densification -------------------------------------------------------------------------------
def fill_nearest(values, measured):
    """Plain nearest-measurement fill, the baseline the edge-aware fill must beat. (H, W) -> (H, W)."""
    _, labels = cv2.distanceTransformWithLabels((~measured).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    ys, xs = np.nonzero(measured)
    index_of_label = np.zeros(labels.max() + 1, np.int64)
    index_of_label[labels[ys, xs]] = np.arange(len(ys))      # each measured pixel has its own label
    nearest = index_of_label[labels]
    return values[ys[nearest], xs[nearest]].astype(np.float32)


def test_edge_aware_fill_keeps_surfaces_apart_better_than_nearest_neighbour():
    # two surfaces meet at a colour edge: a near one (disparity 40) left, a far one (5) right
    h, w = 60, 80
    guide = np.zeros((h, w, 3), np.float32)
    guide[:, 40:] = 0.8
    truth = np.where(np.arange(w) < 40, 40.0, 5.0)[None].repeat(h, 0).astype(np.float32)
    measured = np.zeros((h, w), bool)
    measured[::6, 34] = measured[::6, 52] = True        # measurements only far from the edge
    filled, known = fill_sparse(truth, measured, guide)
    nearest = fill_nearest(truth, measured)
    band = np.s_[:, 36:48]                              # pixels nearer the other side's samples
    assert known[band].all()
    ours = np.abs(filled[band] - truth[band]).mean()
    theirs = np.abs(nearest[band] - truth[band]).mean()
    assert ours < 0.5 and theirs > 5


def test_fill_leaves_far_regions_unknown_and_keeps_measurements():
    values = np.arange(100 * 50, dtype=np.float32).reshape(50, 100) / 50 + 1
    measured = np.zeros((50, 100), bool)
    measured[40:, ::3] = True
    filled, known = fill_sparse(values, measured, np.full((50, 100, 3), 0.5, np.float32), max_gap_px=10)
    np.testing.assert_array_equal(filled[measured], values[measured])
    assert not known[:25].any() and np.isnan(filled[:25]).all()
    assert known[35:].all()


def test_forward_warp_keeps_the_nearest_surface():
    disp = np.array([[10.0, 30.0, 0.0]], np.float32)
    valid = np.array([[True, True, False]])
    flow = np.zeros((1, 3, 2), np.float32)
    flow[0, 0, 0] = 1.2          # pixel 0 lands on pixel 1, where pixel 1 (nearer) stays
    out, hit = forward_warp_disparity(disp, valid, flow)
    np.testing.assert_array_equal(hit, [[False, True, False]])
    assert out[0, 1] == 30.0


# -- the reader ----------------------------------------------------------------------------------
def test_lists_pairs_by_sequence_and_frame(tmp_path, street):
    write_fake_kitti(tmp_path, street[0], scene="000007")
    write_fake_kitti(tmp_path, street[1], scene="000003")
    ds = open_dataset("kitti", tmp_path)
    assert [(r.id.scene, r.id.frame) for r in ds.pairs()] == [("000003", 10), ("000007", 10)]
    assert [r.id.scene for r in open_dataset("kitti", tmp_path, scenes=["000007"]).pairs()] == ["000007"]
    with pytest.raises(ConfigError, match="single rendering pass"):
        open_dataset("kitti", tmp_path, pass_="final")
    with pytest.raises(ConfigError, match="unknown kitti split 'val'"):
        open_dataset("kitti", tmp_path, split="val")


def test_depth_of_both_frames_is_read_back(tmp_path, street):
    truth = street[0]
    write_fake_kitti(tmp_path, truth, object_motion=(0.0, 0.0))
    pair = load_one(tmp_path)
    assert pair.image1.shape == (3, *truth.size) and pair.depth1.dtype == torch.float32
    assert pair.meta["baseline_m"] == pytest.approx(KITTI_BASELINE)
    for depth, true, measured, provenance in (
            (pair.depth1, truth.depth1, pair.depth_measured1, pair.depth_provenance1),
            (pair.depth2, truth.depth2, pair.depth_measured2, pair.depth_provenance2)):
        rel = ((depth - true).abs() / true)[0]
        m = measured[0]
        far = depth[0] == 1000.0
        assert 0.25 < m.float().mean() < 0.5
        assert rel[m].median() < 5e-3
        filled = ~m & ~far
        assert rel[filled].median() < 0.01
        assert rel[filled].quantile(0.9) < 0.05
        assert not far[60:].any()          # sky only above the scan (the street's blue ceiling)
        prov = provenance[0]
        assert ((prov == SKY) == far).all() and ((prov == COMPLETED) == filled).all()
    # frame 1: measurements exact; the band above them is completed (the street's walls) or sky
    assert (pair.depth1 - truth.depth1).abs()[pair.depth_measured1].max() < 2e-3 * truth.depth1.max()
    assert (pair.depth_provenance1[0, :5] != UNKNOWN).all()
    # frame 2: measurements moved with the flow to whole pixels (sub-pixel shifts, a few
    # occlusion leftovers at edges)
    rel2 = ((pair.depth2 - truth.depth2).abs() / truth.depth2)[pair.depth_measured2]
    assert rel2.quantile(0.99) < 0.03
    # frame 1's measured pixels are exactly those written
    disp, valid = read_disparity_png(tmp_path / "training" / "disp_occ_0" / "000000_10.png")
    np.testing.assert_array_equal(pair.depth_measured1[0].numpy(), valid)


def test_camera_motion_is_fitted_on_the_static_background(tmp_path, street):
    truth = street[0]
    write_fake_kitti(tmp_path, truth)      # with a "car" moving on its own
    pair = load_one(tmp_path)
    rot, trans = motion_errors(pair.cam2_from_cam1, truth.cam2_from_cam1)
    assert rot < 0.1 and trans < 0.01
    fit = pair.meta["camera_motion"]
    assert fit["inlier_fraction"] > 0.99 and fit["rms_px"] < 0.1
    assert pair.cam1_from_world is None
    assert pair.flow_valid.any() and pair.flow.shape == (2, *truth.size)


@pytest.mark.parametrize("seed", [0, 1])
def test_camera_motion_survives_20_percent_corrupted_correspondences(tmp_path, street, seed):
    truth = street[1]
    write_fake_kitti(tmp_path, truth, corrupt=0.2, seed=seed)
    pair = load_one(tmp_path)
    rot, trans = motion_errors(pair.cam2_from_cam1, truth.cam2_from_cam1)
    assert rot < 0.1 and trans < 0.01
    assert 0.75 < pair.meta["camera_motion"]["inlier_fraction"] < 0.85


def test_depth_scale_and_zeroed_translation(tmp_path, street):
    truth = street[0]
    write_fake_kitti(tmp_path, truth)
    plain = load_one(tmp_path)
    scaled = load_one(tmp_path, depth_scale=0.5, camera_translation=False)
    torch.testing.assert_close(scaled.depth1, plain.depth1 * 0.5)
    assert scaled.cam2_from_cam1[:3, 3].abs().max() == 0
    torch.testing.assert_close(scaled.cam2_from_cam1[:3, :3], plain.cam2_from_cam1[:3, :3])
    far = load_one(tmp_path, far_depth=250.0)
    assert far.depth1[0, 0].max() == 250.0


# -- bad input -----------------------------------------------------------------------------------
def test_missing_calibration_names_the_file(tmp_path, street):
    s = write_fake_kitti(tmp_path, street[0])
    (s / "calib_cam_to_cam" / "000000.txt").unlink()
    with pytest.raises(DatasetError, match=r"calib_cam_to_cam/000000\.txt: calibration file is missing"):
        load_one(tmp_path)


def test_disparity_of_the_wrong_size_names_the_file(tmp_path, street):
    s = write_fake_kitti(tmp_path, street[0])
    write_disparity_png(s / "disp_occ_1" / "000000_10.png", np.ones((10, 12)))
    h, w = street[0].size
    with pytest.raises(DatasetError, match=rf"disp_occ_1/000000_10\.png: disparity is 12x10 but the frame is {w}x{h}"):
        load_one(tmp_path)


def test_unreadable_disparity_is_one_line_naming_the_file(tmp_path, street):
    s = write_fake_kitti(tmp_path, street[0])
    path = s / "disp_occ_0" / "000000_10.png"
    path.write_bytes(path.read_bytes()[:100])          # truncated download
    ds = open_dataset("kitti", tmp_path)
    message = ds.check(ds.pairs()[0])
    assert message == f"{path}: cannot be decoded as an image (corrupt or not an image)"


def test_too_few_static_points_is_refused(tmp_path, street):
    s = write_fake_kitti(tmp_path, street[0])
    objects = np.ones(street[0].size, np.uint8)
    objects[:2, :50] = 0
    write_object_map(s / "obj_map" / "000000_10.png", objects)
    with pytest.raises(DatasetError, match=r"obj_map/000000_10\.png: camera motion of pair 000000 \(frames 10-11\): "
                                            r"only \d+ static pixels \(obj_map 0\) with flow and frame-10 disparity; "
                                            r"the fit needs at least 200"):
        load_one(tmp_path)


def test_a_bad_fit_is_refused_with_its_residual(tmp_path, street):
    write_fake_kitti(tmp_path, street[0], corrupt=0.7)
    with pytest.raises(DatasetError, match=r"flow_occ/000000_10\.png: camera motion of pair 000000 "
                                            r"\(frames 10-11\) is not trusted: only \d+\.\d% of \d+ "
                                            r"correspondences agree with one camera motion within 2 px"):
        load_one(tmp_path)


def test_testing_split_says_what_is_missing(tmp_path, street):
    write_fake_kitti(tmp_path, street[0], split="testing")
    ds = open_dataset("kitti", tmp_path, split="testing")
    assert len(ds.pairs()) == 1
    with pytest.raises(DatasetError, match="testing split ships no disparity or flow"):
        ds.load(ds.pairs()[0])


def test_a_missing_second_frame_is_reported_not_hidden(tmp_path, street):
    s = write_fake_kitti(tmp_path, street[0])
    (s / "image_2" / "000000_11.png").unlink()
    ds = open_dataset("kitti", tmp_path)
    assert [r.id.scene for r in ds.pairs()] == ["000000"]
    assert ds.check(ds.pairs()[0]).endswith("image_2/000000_11.png: second frame file is missing")
    assert open_dataset("kitti", tmp_path, first_frame=11).pairs() == []


@pytest.mark.parametrize("option, message", [
    (dict(fit_min_points=2), "minimum fit points must be at least 6, got 2"),
    (dict(fit_min_inlier_fraction=1.5), r"minimum inlier fraction must be in \(0, 1\], got 1.5"),
    (dict(fit_min_inlier_fraction=0), r"minimum inlier fraction must be in \(0, 1\], got 0"),
    (dict(fit_threshold_px=-1.0), "fit threshold must be a positive number of pixels, got -1.0"),
    (dict(fit_max_rms_px=0.0), "maximum fit RMS must be a positive number of pixels, got 0.0"),
    (dict(max_gap_px=-3), "max_gap_px must be zero or positive, got -3"),
])
def test_fit_and_fill_options_are_validated(tmp_path, option, message):
    (tmp_path / "training" / "image_2").mkdir(parents=True)
    with pytest.raises(ConfigError, match=message):
        open_dataset("kitti", tmp_path, **option)


def test_missing_layout(tmp_path):
    with pytest.raises(DatasetError, match="expected KITTI 2015 layout"):
        open_dataset("kitti", tmp_path).pairs()


# -- the command line ----------------------------------------------------------------------------
def run_cli(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, args)


def test_check_command_reads_kitti(tmp_path, street):
    write_fake_kitti(tmp_path, street[0], scene="000000")
    write_fake_kitti(tmp_path, street[1], scene="000001")
    result = run_cli(["check", "--dataset", "kitti", "--root", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert "All 2 pairs in 2 scenes are readable" in result.output

    (tmp_path / "training" / "calib_cam_to_cam" / "000001.txt").unlink()
    result = run_cli(["check", "--dataset", "kitti", "--root", str(tmp_path), "--far-depth", "300"])
    assert result.exit_code == 1
    assert "000001: calibration file is missing: training/calib_cam_to_cam/000001.txt" in result.output


def test_check_command_explains_the_testing_split(tmp_path, street):
    write_fake_kitti(tmp_path, street[0], split="testing")
    result = run_cli(["check", "--dataset", "kitti", "--root", str(tmp_path), "--split", "testing"])
    assert result.exit_code == 1
    assert "testing split ships no disparity or flow" in result.output.replace("\n", " ")


def test_far_depth_does_not_apply_to_sintel(fake_sintel):
    result = run_cli(["check", "--root", str(fake_sintel), "--far-depth", "300"])
    assert result.exit_code == 2
    assert "--far-depth does not apply to sintel" in result.output


def test_render_manifest_reports_the_pose_fit(tmp_path, street):
    import json

    write_fake_kitti(tmp_path / "kitti", street[0], scene="000002")
    out = tmp_path / "out"
    res = run_cli(["render", "--dataset", "kitti", "--root", str(tmp_path / "kitti"), "--out", str(out),
                   "--set", "count=100"])
    assert res.exit_code == 0, res.output
    entry = json.loads((out / "manifest.json").read_text())["pairs"]["kitti:training:000002:10"]
    fit = entry["input"]["camera_motion"]
    assert fit["inliers"] > 0 and 0 <= fit["rms_px"] < fit["threshold_px"]
