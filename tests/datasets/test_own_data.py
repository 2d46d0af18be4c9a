"""Own data (custom layout): frame names of any kind, depth sign conventions, partly missing depth."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from fake_datasets import demo_sequence, write_fake_custom
from weathergen.datasets import open_dataset
from weathergen.datasets.framenames import order_frames
from weathergen.errors import DatasetError
from weathergen.framepair import COMPLETED, SKY
from weathergen.io.custom_formats import read_depth, write_depth
from weathergen.io.images import write_png


@pytest.fixture(scope="module")
def street(demo_root):
    return demo_sequence("street")


def run_cli(*args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, list(args))


# -- ordering names ------------------------------------------------------------------------------
@pytest.mark.parametrize("names, expected, numbering", [
    (["000001_left.png", "000000_left.png", "000002_left.png"],
     [(0, "000000_left.png"), (1, "000001_left.png"), (2, "000002_left.png")], "name"),
    (["frame10.png", "frame9.png", "notes.txt"], [(9, "frame9.png"), (10, "frame10.png")], "name"),
    (["cam0_2023-05-01_12-00-10.jpg", "cam0_2023-05-01_12-00-02.jpg", "cam0_2023-05-01_11-59-58.jpg"],
     [(0, "cam0_2023-05-01_11-59-58.jpg"), (1, "cam0_2023-05-01_12-00-02.jpg"),
      (2, "cam0_2023-05-01_12-00-10.jpg")], "position"),
    (["b.png", "a.png", "c.PNG"], [(0, "a.png"), (1, "b.png"), (2, "c.PNG")], "position"),
])
def test_frames_are_ordered_whatever_their_names(names, expected, numbering):
    order = order_frames(names)
    assert order.problem is None and list(order.frames) == expected and order.numbering == numbering


@pytest.mark.parametrize("names, pattern, problem", [
    (["000000_left.png", "000000_right.png", "000001_left.png", "000001_right.png"], None,
     "holds frames named in 2 ways, which cannot be put in one order without guessing: "
     "'#_left.png': 2 files (000000_left.png, 000001_left.png); '#_right.png': 2 files "
     "(000000_right.png, 000001_right.png); choose one with a frame pattern (e.g. --frame-pattern '*_left.png')"),
    (["0001.png", "0002.png", "cover.png"], None, "holds frames named in 2 ways"),
    (["0001.png"], None, "holds a single frame (0001.png); a pair needs two"),
    (["a.tif", "b.tif", "notes.txt"], None, "holds no image files (.png, .jpg, .jpeg); found 2 .tif, 1 .txt"),
    (["0001.png", "0002.png"], "*_left.png",
     "no file matches the frame pattern '*_left.png' (2 files there: 0001.png, 0002.png)"),
    (["f01.png", "f1.png"], None, "frames f01.png and f1.png have the same number 1"),
])
def test_why_frames_cannot_be_paired(names, pattern, problem):
    order = order_frames(names, pattern)
    assert order.frames == () and order.problem.startswith(problem)


def test_a_pattern_picks_one_kind():
    order = order_frames(["000000_left.png", "000000_right.png", "000001_left.png"], "*_left.png")
    assert list(order.frames) == [(0, "000000_left.png"), (1, "000001_left.png")]


# -- the reader and check ------------------------------------------------------------------------
def test_unusual_names_are_paired_and_cameras_found_by_number_or_stem(tmp_path, street):
    frames, pairs = street
    for name, stem_keys in (("numbers", False), ("stems", True)):
        root = write_fake_custom(tmp_path / name, frames, stem=lambda i: f"{i:06d}_left",
                                 stem_keys=stem_keys)
        ds = open_dataset("custom", root)
        assert [r.id.frame for r in ds.pairs()] == [0, 1, 2]
        pair = ds.load(ds.pairs()[1])
        torch.testing.assert_close(pair.cam2_from_cam1, pairs[1].cam2_from_cam1, atol=1e-9, rtol=0)
        assert pair.sources["image1"].name == "000001_left.png"


def test_left_and_right_images_in_one_folder_are_explained_and_a_pattern_fixes_it(tmp_path, street):
    frames, _ = street
    root = write_fake_custom(tmp_path / "stereo", frames, stem=lambda i: f"{i:06d}_left")
    for i, fr in enumerate(frames):
        write_png(root / "frames" / f"{i:06d}_right.png", fr["image"])
    res = run_cli("check", "--dataset", "custom", "--root", str(root))
    assert res.exit_code == 1
    assert "stereo: frames cannot be paired: holds frames named in 2 ways, which cannot be put in one " \
           "order without guessing" in res.output
    assert "--frame-pattern '*_left.png'" in res.output and "1 scene without pairs: stereo" in res.output
    res = run_cli("render", "--dataset", "custom", "--root", str(root), "--out", str(tmp_path / "out"))
    assert res.exit_code == 2 and "holds frames named in 2 ways" in res.output
    res = run_cli("check", "--dataset", "custom", "--root", str(root), "--frame-pattern", "*_left.png")
    assert res.exit_code == 0, res.output
    assert "All 3 pairs in 1 scene are readable" in res.output
    res = run_cli("check", "--root", str(root), "--frame-pattern", "*_left.png")
    assert res.exit_code == 2 and "--frame-pattern applies to custom only, not to sintel" in res.output


def test_one_unpairable_scene_does_not_hide_the_others(tmp_path, street):
    frames, _ = street
    write_fake_custom(tmp_path / "good", frames)
    write_fake_custom(tmp_path / "lonely", frames[:1])
    ds = open_dataset("custom", tmp_path)
    assert {r.id.scene for r in ds.pairs()} == {"good"}
    assert "holds a single frame (0000.png)" in ds.scene_problems()["lonely"][0].kind
    res = run_cli("check", "--dataset", "custom", "--root", str(tmp_path))
    assert res.exit_code == 1
    assert "lonely: frames cannot be paired: holds a single frame (0000.png); a pair needs two: lonely/frames" \
        in res.output


def test_all_negative_depth_is_an_error_with_a_sign_hint(tmp_path, street):
    frames, _ = street
    root = write_fake_custom(tmp_path / "neg", frames[:2])
    path = root / "depth" / "0001.npy"
    write_depth(path, -read_depth(path))
    with pytest.raises(DatasetError, match=r"0001\.npy: no valid depth in this frame; 100% of its values are "
                                           r"negative: negative depth is counted as missing; depth must be "
                                           r"the positive camera-z distance .*negate them"):
        ds = open_dataset("custom", root)
        ds.load(ds.pairs()[0])
    res = run_cli("check", "--dataset", "custom", "--root", str(root))
    assert res.exit_code == 1 and "no valid depth in this frame; 100% of its values are negative" in res.output


def test_partly_missing_or_negative_depth_warns_and_lists_every_frame(tmp_path, street):
    frames, _ = street
    root = write_fake_custom(tmp_path / "holes", frames)
    h = frames[0]["depth"].shape[0]
    for i in (0, 2):            # 70 % of frames 0 and 2 missing (NaN), frame 3 a quarter negative
        path = root / "depth" / f"{i:04d}.npy"
        d = read_depth(path)
        d[: int(0.7 * h)] = np.nan
        write_depth(path, d)
    path = root / "depth" / "0003.npy"
    d = read_depth(path)
    d[: h // 4] *= -1
    write_depth(path, d)
    ds = open_dataset("custom", root)
    pair = ds.load(ds.pairs()[0])
    assert pair.meta["depth_values"][0]["valid"] == pytest.approx(0.3, abs=0.01)
    assert pair.depth_measured1.float().mean() == pytest.approx(0.3, abs=0.01)
    # the missing band is completed (a street's walls, no sky), or is sky at the far depth
    prov = pair.depth_provenance1[0]
    assert ((prov == COMPLETED) | (prov == SKY))[: int(0.7 * h)].all()
    assert (pair.depth1[0][prov == SKY] == ds.far_depth).all()
    assert (pair.depth1[0][prov == COMPLETED] < ds.far_depth).all()
    assert pair.meta["depth_values"][0]["filled"] == pytest.approx(float((prov == COMPLETED).float().mean()),
                                                                  abs=1e-4)
    res = run_cli("check", "--dataset", "custom", "--root", str(root))
    assert res.exit_code == 0, res.output             # warnings do not fail
    out = res.output.replace(f"{root}/", "")
    assert re.search(r"holes: warning: less than 50% of the depth is valid \(the rest is sky or "
                     r"completed from the valid pixels\): "
                     r"depth/0000\.npy \(30% valid\), depth/0002\.npy \(30% valid\)$", out, re.M), out
    assert "holes: warning: negative depth is counted as missing" in out and "depth/0003.npy (25% negative)" in out
    res = run_cli("check", "--dataset", "custom", "--root", str(root), "--min-valid-depth", "0.2")
    assert res.exit_code == 0 and "less than" not in res.output


def test_depth_and_flow_named_differently_are_found_by_the_frame_number(tmp_path, street):
    # RGB-D exports often name each kind of file apart: frame-000000.color.jpg, frame-000000.depth.png
    frames, pairs = street
    root = write_fake_custom(tmp_path / "kitchen", frames, stem=lambda i: f"frame-{i:06d}.color",
                             flows=pairs)
    for i in range(len(frames)):
        (root / "depth" / f"frame-{i:06d}.color.npy").rename(root / "depth" / f"frame-{i:06d}.depth.npy")
        if i < len(pairs):
            (root / "flow" / f"frame-{i:06d}.color.flo").rename(root / "flow" / f"frame-{i:06d}.flow.flo")
    ds = open_dataset("custom", root)
    ref = ds.pairs()[1]
    assert ref.files["depth1"].name == "frame-000001.depth.npy"
    assert ref.files["depth2"].name == "frame-000002.depth.npy"
    assert ref.files["flow"].name == "frame-000001.flow.flo"
    pair = ds.load(ref)
    torch.testing.assert_close(pair.depth1, pairs[1].depth1, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(pair.depth2, pairs[1].depth2, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(pair.flow, pairs[1].flow)


def test_missing_depth_says_how_depth_files_are_found(tmp_path, street):
    frames, _ = street
    root = write_fake_custom(tmp_path / "kitchen", frames[:2], stem=lambda i: f"frame-{i:06d}.color")
    for i in range(2):      # two depth files whose number matches no frame: not taken by position
        (root / "depth" / f"frame-{i:06d}.color.npy").rename(root / "depth" / f"frame-{i + 5:06d}.depth.npy")
    ds = open_dataset("custom", root)
    assert ds.pairs()[0].files["depth1"].name == "frame-000000.color.npy"
    res = run_cli("check", "--dataset", "custom", "--root", str(root))
    assert res.exit_code == 1
    assert "kitchen: depth file is missing (a depth file is the frame's name with .npy, .png or .exr in " \
           "depth/, or a file there with the frame's number" in res.output
    res = run_cli("render", "--dataset", "custom", "--root", str(root), "--out", str(tmp_path / "out"))
    assert res.exit_code == 2 and "frame-1 depth file is missing (a depth file is the frame's name" in res.output


def test_fill_gaps_option_reaches_the_reader(tmp_path, street, monkeypatch):
    from weathergen.datasets import custom

    frames, _ = street
    root = write_fake_custom(tmp_path / "s", frames[:2], missing=(0, 10))
    seen = []
    original = custom.CustomDataset.__init__

    def spy(self, *args, **kwargs):
        original(self, *args, **kwargs)
        seen.append(self.max_gap_px)

    monkeypatch.setattr(custom.CustomDataset, "__init__", spy)
    assert run_cli("check", "--dataset", "custom", "--root", str(root), "--fill-gaps", "0").exit_code == 0
    assert run_cli("check", "--dataset", "custom", "--root", str(root)).exit_code == 0
    assert seen == [0.0, 24.0]
    res = run_cli("check", "--fill-gaps", "3")
    assert res.exit_code == 2 and "--fill-gaps applies to custom, kitti only, not to demo" in res.output
