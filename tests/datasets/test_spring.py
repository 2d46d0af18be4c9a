"""Spring: HDF5 formats, the 2x ground-truth resolution, cameras and every bad-input path."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from fake_datasets import demo_sequence, write_fake_spring
from weathergen.datasets import open_dataset
from weathergen.errors import ConfigError, DatasetError, FormatError
from weathergen.geometry import invert_rigid, reprojection_flow
from weathergen.io.spring_formats import (read_dsp5, read_extrinsics_txt, read_flo5,
                                          read_intrinsics_txt, reduce_2x2, write_dsp5,
                                          write_extrinsics_txt, write_flo5, write_intrinsics_txt)


@pytest.fixture(scope="module")
def street(demo_root):
    return demo_sequence("street")


def load(root, frame=1, **options):
    ds = open_dataset("spring", root, split="train", **options)
    ref = next(r for r in ds.pairs() if r.id.frame == frame)
    return ds.load(ref)


SCENE = "train/0001"


# -- formats -------------------------------------------------------------------------------------
def test_hdf5_round_trips(tmp_path):
    disp = np.random.default_rng(0).random((6, 8)).astype(np.float32)
    disp[0, 0] = np.nan
    write_dsp5(tmp_path / "d.dsp5", disp)
    np.testing.assert_array_equal(read_dsp5(tmp_path / "d.dsp5"), disp)
    flow = np.random.default_rng(1).normal(size=(6, 8, 2)).astype(np.float32)
    write_flo5(tmp_path / "f.flo5", flow)
    np.testing.assert_array_equal(read_flo5(tmp_path / "f.flo5"), flow)
    with h5py.File(tmp_path / "d.dsp5", "r") as f:
        assert list(f.keys()) == ["disparity"]


def test_hdf5_without_the_expected_dataset_is_named(tmp_path):
    write_flo5(tmp_path / "wrong.dsp5", np.zeros((4, 4, 2)))
    with pytest.raises(FormatError, match=r"wrong\.dsp5: has no 'disparity' dataset \(found: flow\)"):
        read_dsp5(tmp_path / "wrong.dsp5")
    (tmp_path / "text.flo5").write_text("not hdf5")
    with pytest.raises(FormatError, match=r"text\.flo5: cannot be read as HDF5"):
        read_flo5(tmp_path / "text.flo5")
    write_dsp5(tmp_path / "flat.flo5", np.zeros((4, 4)))
    with pytest.raises(FormatError, match=r"flat\.flo5: has no 'flow' dataset"):
        read_flo5(tmp_path / "flat.flo5")


def test_camera_text_files(tmp_path):
    write_intrinsics_txt(tmp_path / "i.txt", [[1000, 1000, 960, 540], [1001, 1001, 960, 540]])
    np.testing.assert_allclose(read_intrinsics_txt(tmp_path / "i.txt")[1], [1001, 1001, 960, 540])
    mats = np.stack([np.eye(4), np.eye(4)])
    mats[1, :3, 3] = (1, 2, 3)
    write_extrinsics_txt(tmp_path / "e.txt", mats)
    np.testing.assert_allclose(read_extrinsics_txt(tmp_path / "e.txt"), mats)
    (tmp_path / "bad.txt").write_text("1 2 3 4 5\n")
    with pytest.raises(FormatError, match=r"bad\.txt: holds 5 numbers, expected 16 per frame"):
        read_extrinsics_txt(tmp_path / "bad.txt")
    (tmp_path / "skew.txt").write_text(" ".join(["2"] * 12 + ["0", "0", "0", "1"]) + "\n")
    with pytest.raises(FormatError, match=r"skew\.txt: matrix 1 is not a rigid transform"):
        read_extrinsics_txt(tmp_path / "skew.txt")


# -- 2x2 reduction -------------------------------------------------------------------------------
def test_reduce_2x2_ignores_invalid_samples_and_outliers():
    grid = np.array([[5.0, np.nan, 7.0, 7.0],
                     [5.0, 5.0, 7.0, 900.0],
                     [np.nan, np.nan, 1.0, 1.0],
                     [np.nan, np.nan, 9.0, 9.0]], np.float32)
    valid = np.isfinite(grid)
    out, ok = reduce_2x2(grid, valid)
    np.testing.assert_array_equal(ok, [[True, True], [False, True]])
    assert out[0, 0] == 5.0 and out[0, 1] == 7.0
    assert np.isnan(out[1, 0])
    assert out[1, 1] in (1.0, 9.0)            # a real sample at an edge, never the mean 5


def test_reduce_2x2_keeps_vectors_whole():
    flow = np.zeros((2, 2, 2), np.float32)
    flow[..., 0] = [[1, 1], [2, 50]]
    flow[..., 1] = [[3, 3], [4, -40]]
    out, ok = reduce_2x2(flow, np.ones((2, 2), bool))
    assert ok.all()
    np.testing.assert_array_equal(out[0, 0], [1, 3])


# -- the reader ----------------------------------------------------------------------------------
def test_depth_flow_and_cameras_from_double_resolution_files(tmp_path, street):
    frames, pairs = street
    write_fake_spring(tmp_path, frames, pairs=pairs, holes=0.3, outliers=0.3)
    ds = open_dataset("spring", tmp_path, split="training")
    assert [(r.id.scene, r.id.frame) for r in ds.pairs()] == [("0001", 1), ("0001", 2), ("0001", 3)]
    pair = load(tmp_path, frame=2)
    truth = pairs[1]
    assert pair.size == truth.size
    torch.testing.assert_close(pair.depth1, truth.depth1, rtol=1e-5, atol=0)
    torch.testing.assert_close(pair.depth2, truth.depth2, rtol=1e-5, atol=0)
    assert pair.depth_measured1.all() and pair.depth_measured2.all()
    torch.testing.assert_close(pair.flow, truth.flow)
    assert pair.flow_valid.all()
    torch.testing.assert_close(pair.cam2_from_cam1, truth.cam2_from_cam1)
    torch.testing.assert_close(pair.cam1_from_world, truth.cam1_from_world)
    # the extrinsics convention is right: the static scene's flow is the cameras' reprojection
    static = reprojection_flow(pair.depth1.double(), pair.intrinsics, pair.cam2_from_cam1)
    assert (static - pair.flow).abs().max() < 1e-3


def test_frame_resolution_files_are_taken_as_they_are_and_flow_is_optional(tmp_path, street):
    frames, pairs = street
    write_fake_spring(tmp_path, frames, gt_factor=1)
    pair = load(tmp_path)
    torch.testing.assert_close(pair.depth1, pairs[0].depth1, rtol=1e-5, atol=0)
    assert pair.flow is None and pair.flow_valid is None


def test_sky_without_disparity_gets_far_depth(tmp_path, street):
    frames, _ = street
    write_fake_spring(tmp_path, frames)
    path = tmp_path / SCENE / "disp1_left" / "disp1_left_0001.dsp5"
    disp = read_dsp5(path)
    disp[:20] = np.nan
    disp[20:30] = 0.0
    write_dsp5(path, disp)
    pair = load(tmp_path, far_depth=500.0)
    assert (pair.depth1[0, :15] == 500.0).all()
    assert not pair.depth_measured1[0, :15].any() and pair.depth_measured1[0, 15:].all()


def test_camera_to_world_extrinsics_option(tmp_path, street):
    frames, pairs = street
    inverted = [dict(fr, cam=invert_rigid(torch.from_numpy(fr["cam"])).numpy()) for fr in frames]
    write_fake_spring(tmp_path, inverted)
    pair = load(tmp_path, extrinsics="camera-to-world")
    torch.testing.assert_close(pair.cam2_from_cam1, pairs[0].cam2_from_cam1)
    with pytest.raises(ConfigError, match="unknown Spring extrinsics convention 'sideways'"):
        open_dataset("spring", tmp_path, split="train", extrinsics="sideways")


# -- bad input -----------------------------------------------------------------------------------
def test_disparity_of_the_wrong_size_names_the_file(tmp_path, street):
    frames, _ = street
    write_fake_spring(tmp_path, frames, gt_factor=3)
    h, w = frames[0]["depth"].shape
    with pytest.raises(DatasetError, match=rf"disp1_left_0001\.dsp5: disparity is {3 * w}x{3 * h} but "
                                           rf"the frame is {w}x{h}; expected {2 * w}x{2 * h}"):
        load(tmp_path)


def test_missing_extrinsics_and_short_camera_files(tmp_path, street):
    frames, _ = street
    write_fake_spring(tmp_path, frames)
    cam = tmp_path / SCENE / "cam_data"
    write_extrinsics_txt(cam / "extrinsics.txt", np.stack([fr["cam"] for fr in frames[:2]]))
    with pytest.raises(DatasetError, match=r"extrinsics\.txt: has 2 frames, but frame 3 is needed"):
        load(tmp_path, frame=2)
    (cam / "extrinsics.txt").unlink()
    with pytest.raises(DatasetError, match=r"cam_data/extrinsics\.txt: extrinsics file is missing"):
        load(tmp_path)


def test_a_zoom_inside_a_pair_is_refused(tmp_path, street):
    frames, _ = street
    write_fake_spring(tmp_path, frames)
    write_intrinsics_txt(tmp_path / SCENE / "cam_data" / "intrinsics.txt",
                         [[300, 300, 191.5, 87.5], [330, 330, 191.5, 87.5], [330, 330, 191.5, 87.5],
                          [330, 330, 191.5, 87.5]])
    with pytest.raises(DatasetError, match=r"intrinsics\.txt: frames 1 and 2 have different intrinsics"):
        load(tmp_path)


def test_hdf5_without_disparity_dataset_in_a_tree(tmp_path, street):
    frames, _ = street
    write_fake_spring(tmp_path, frames)
    write_flo5(tmp_path / SCENE / "disp1_left" / "disp1_left_0002.dsp5", np.zeros((4, 4, 2)))
    with pytest.raises(FormatError, match=r"disp1_left_0002\.dsp5: has no 'disparity' dataset"):
        load(tmp_path)


def test_test_split_without_ground_truth(tmp_path, street):
    frames, _ = street
    write_fake_spring(tmp_path, frames)
    (tmp_path / "train").rename(tmp_path / "test")
    for p in (tmp_path / "test" / "0001" / "disp1_left").iterdir():
        p.unlink()
    ds = open_dataset("spring", tmp_path, split="test")
    with pytest.raises(DatasetError, match="Spring test split ships no disparity, so it has no depth"):
        ds.load(ds.pairs()[0])


def test_check_command_reads_spring(tmp_path, street):
    from weathergen.cli.main import _register, cli

    frames, pairs = street
    write_fake_spring(tmp_path, frames, pairs=pairs)
    _register()
    result = CliRunner().invoke(cli, ["check", "--dataset", "spring", "--root", str(tmp_path),
                                      "--split", "train"])
    assert result.exit_code == 0, result.output
    assert "All 3 pairs in 1 scene are readable" in result.output


def test_render_writes_spring_flow_in_springs_own_format(tmp_path, street):
    from click.testing import CliRunner

    from weathergen.cli.main import _register, cli
    from weathergen.io.spring_formats import read_flo5

    frames, pairs = street
    write_fake_spring(tmp_path / "spring", frames, pairs=pairs)
    out = tmp_path / "out"
    _register()
    res = CliRunner().invoke(cli, ["render", "--dataset", "spring", "--root", str(tmp_path / "spring"),
                                   "--split", "train", "--frames-per-scene", "1", "--set", "count=100",
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    # The output is a Sintel tree: Spring's "train" split becomes Sintel's "training" folder.
    native = read_flo5(out / "training/flow_FW_left/0001_0001/frame_0001.flo5")
    truth = pairs[0].flow.permute(1, 2, 0).numpy()
    np.testing.assert_allclose(native, truth, atol=1e-5)
    res = CliRunner().invoke(cli, ["check", "--dataset", "sintel", "--root", str(out), "--pass", "snow_clean"])
    assert res.exit_code == 0, res.output
    assert "1 pair in 1 scene is readable" in res.output
