"""Cases a user trial found silent: each now says what happened (one test per case).

Each test fails on the code before its fix; they run the commands on tiny fake datasets or the
demo scene.
"""

from __future__ import annotations

import json
import re

import pytest
from click.testing import CliRunner

from weathergen.cli.main import cli


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


# -- a gap in a scene's frame numbering ------------------------------------------------------------

@pytest.fixture
def sintel_with_a_gap(fake_sintel):
    """Scene alley without frame 2 (frames 1, 3, 4): pairs 1 and 2 cannot be formed."""
    for p in fake_sintel.rglob("alley/frame_0002.*"):
        p.unlink()
    return fake_sintel


def test_check_and_render_report_a_gap_in_a_scenes_frame_numbering(sintel_with_a_gap, tmp_path):
    root = sintel_with_a_gap
    res = run("check", "--root", root, "--scenes", "alley")
    assert res.exit_code == 0, res.output
    assert ("alley: warning: gap in the frame numbering: no frame 2, so the pairs of frames 1-2, 2-3 "
            "cannot be formed") in res.output, res.output
    # --frames-per-scene 1 takes pair 3 in place of pair 1: said, with where
    res = run("render", "--root", root, "--scenes", "alley", "--frames-per-scene", "1", "--set",
              "count=20", "--out", tmp_path / "o", "-q")
    assert res.exit_code == 0, res.output
    assert (f"Note: {root / 'training' / 'clean' / 'alley'}: gap in the frame numbering: no frame 2, "
            f"so the pair of frames 1-2 cannot be formed and the selection takes the pair of frames "
            f"3-4 instead") in res.output
    # and records it in the manifest, under the run (as a pair's warnings are under the pair)
    runs = json.loads((tmp_path / "o" / "manifest.json").read_text())["runs"]
    assert runs[-1]["notes"] == [f"{root / 'training' / 'clean' / 'alley'}: gap in the frame "
                                 "numbering: no frame 2, so the pair of frames 1-2 cannot be formed "
                                 "and the selection takes the pair of frames 3-4 instead"]
    # a selection the gap does not touch says nothing
    res = run("check", "--root", root, "--scenes", "alley", "--first-frame", "3")
    assert res.exit_code == 0 and "gap" not in res.output, res.output


@pytest.mark.slow
def test_attack_and_benchmark_report_a_gap_too(sintel_with_a_gap, tmp_path, raft_small_weights):
    """The paper's selections are --frames-per-scene 5 attacks: a gap changes theirs as well."""
    root = sintel_with_a_gap
    note = (f"Note: {root / 'training' / 'clean' / 'alley'}: gap in the frame numbering: no frame 2, "
            f"so the pair of frames 1-2 cannot be formed and the selection takes the pair of frames "
            f"3-4 instead")
    common = ("--root", root, "--scenes", "alley", "--frames-per-scene", "1", "--steps", "1",
              "--set", "count=20", "-q")
    res = run("attack", *common, "--model", "raft-small", "--checkpoint", raft_small_weights,
              "--iters", "2", "--out", tmp_path / "a")
    assert res.exit_code == 0, res.output
    assert res.output.count(note) == 1, res.output
    runs = json.loads((tmp_path / "a" / "manifest.json").read_text())["runs"]
    assert [note.removeprefix("Note: ")] == runs[-1]["notes"]
    res = run("benchmark", *common, "--networks", "raft-small", "--checkpoint",
              f"raft-small={raft_small_weights}", "--presets", "snow,rain", "--lp", "",
              "--iters", "2", "--out", tmp_path / "b")
    assert res.exit_code == 0, res.output
    assert res.output.count(note) == 1, res.output          # once, not once per run of the grid


def test_a_gap_names_the_pairs_it_removes_by_their_frames():
    from weathergen.datasets.base import Selection, numbering_gap

    frames = [1, 2, 3, 8, 9, 10]                         # 4 to 7 missing: pairs 3-4 ... 7-8 lost
    assert numbering_gap(Selection(), frames) == (
        "gap in the frame numbering: no frames 4-7, so the pairs of frames 3-4 to 7-8 cannot be "
        "formed")
    assert numbering_gap(Selection(frames_per_scene=3), frames) == (
        "gap in the frame numbering: no frames 4-7, so the pair of frames 3-4 cannot be formed and "
        "the selection takes the pair of frames 8-9 instead")
    assert numbering_gap(Selection(), [1, 2, 4, 6, 7]) == (
        "gap in the frame numbering: no frames 3, 5, so the pairs of frames 2-3 to 5-6 cannot be "
        "formed")
    assert numbering_gap(Selection(), [1, 2, 3]) is None


# -- frames of a pair that differ in channels ------------------------------------------------------

def test_a_pair_of_a_grey_and_a_colour_frame_is_warned_about(fake_sintel, tmp_path):
    from weathergen.io.images import read_image, write_png

    grey = fake_sintel / "training" / "clean" / "alley" / "frame_0002.png"
    write_png(grey, read_image(grey).mean(axis=2))          # stored with one channel
    res = run("render", "--root", fake_sintel, "--scenes", "alley", "--frames-per-scene", "1",
              "--set", "count=20", "--out", tmp_path / "o", "-q")
    assert res.exit_code == 0, res.output
    assert (f"warning sintel/training/alley/0001: {grey}: the second frame is grey but the first "
            f"(frame_0001.png) is colour") in res.output, res.output
    res = run("check", "--root", fake_sintel, "--scenes", "alley")
    assert res.exit_code == 0, res.output
    assert "alley: warning: the second frame is grey but the first (frame_0001.png) is colour" in res.output
    assert "alley: warning: the second frame is colour but the first (frame_0002.png) is grey" in res.output
    # frames of one kind say nothing
    res = run("check", "--root", fake_sintel, "--scenes", "bamboo")
    assert res.exit_code == 0 and "warning" not in res.output, res.output


@pytest.mark.slow
def test_an_attack_on_a_grey_and_a_colour_frame_warns_too(fake_sintel, tmp_path, raft_small_weights):
    from weathergen.io.images import read_image, write_png

    grey = fake_sintel / "training" / "clean" / "alley" / "frame_0002.png"
    write_png(grey, read_image(grey).mean(axis=2))
    out = tmp_path / "a"
    res = run("attack", "--root", fake_sintel, "--scenes", "alley", "--frames-per-scene", "1",
              "--steps", "1", "--set", "count=20", "--model", "raft-small", "--checkpoint",
              raft_small_weights, "--iters", "2", "--out", out, "-q")
    assert res.exit_code == 0, res.output
    said = (f"{grey}: the second frame is grey but the first (frame_0001.png) is colour; both are "
            f"read as RGB (grey replicated to three channels)")
    assert f"warning sintel/training/alley/0001: {said}" in res.output, res.output
    entry = json.loads((out / "manifest.json").read_text())["pairs"]["sintel:training:alley:1"]
    assert entry["status"] == "written" and entry["warnings"] == [said]
    # a resumed run keeps the warning in the manifest
    res = run("attack", "--root", fake_sintel, "--scenes", "alley", "--frames-per-scene", "1",
              "--steps", "1", "--set", "count=20", "--model", "raft-small", "--checkpoint",
              raft_small_weights, "--iters", "2", "--out", out, "-q", "--resume")
    assert res.exit_code == 0, res.output
    entry = json.loads((out / "manifest.json").read_text())["pairs"]["sintel:training:alley:1"]
    assert entry["warnings"] == [said]


# -- an attack without steps ---------------------------------------------------------------------

@pytest.mark.parametrize("command", [
    ("attack", "--steps", "0"), ("attack", "--method", "pcfa", "--steps", "0"),
    ("attack", "--steps", "0", "--method", "pcfa"), ("benchmark", "--steps", "0"),
    ("benchmark", "--lp-steps", "0")])
def test_an_attack_of_zero_steps_is_refused_naming_its_start(tmp_path, command):
    out = tmp_path / "o"
    res = run(*command, "--model", "raft-small", "--out", out) if command[0] == "attack" else \
        run(*command, "--networks", "raft-small", "--out", out)
    assert res.exit_code == 2, res.output
    line = res.output.strip().splitlines()[-1]
    start = "the clean frames" if "--lp-steps" in command or "pcfa" in command else "random weather"
    assert "at least one step" in line and start in line, res.output
    assert not out.exists()


# -- a depth scale that is not a finite number -------------------------------------------------

@pytest.mark.parametrize("value", ["inf", "nan"])
def test_an_infinite_depth_scale_names_the_option_not_the_depth_file(tmp_path, value, demo_root):
    res = run("render", "--depth-scale", value, "--out", tmp_path / "o", "-q")
    assert res.exit_code == 2, res.output
    assert res.output.strip().splitlines() == [
        f"Error: --depth-scale must be a positive finite number, got {value}"], res.output
    assert not (tmp_path / "o").exists()
    table = tmp_path / "scales.toml"
    table.write_text(f"street = {value}\n")
    res = run("check", "--scene-scales", table)
    assert res.exit_code == 2 and f"{table}: scale of scene 'street' must be a positive finite " \
        f"number, got {value}" in res.output, res.output


# -- an empty selection --------------------------------------------------------------------------

def test_an_empty_selection_names_the_options_that_emptied_it(tmp_path, demo_root):
    said = ("the selection holds no frame pairs (--scenes street, --first-frame 9); without "
            "--first-frame the pairs start at frames 1 to 3")
    for command in ("check", "render", "attack"):
        extra = ("--model", "raft-small") if command == "attack" else ()
        if command != "check":
            extra += ("--out", tmp_path / command)
        res = run(command, "--scenes", "street", "--first-frame", "9", *extra)
        assert res.exit_code == 2, res.output
        assert res.output.strip().splitlines()[-1] == f"Error: {demo_root}: {said}", res.output
        assert not (tmp_path / command).exists()
    res = run("render", "--frames-per-scene", "1", "--shard", "3/3", "--out", tmp_path / "o")
    assert res.exit_code == 2 and res.output.strip().splitlines()[-1] == (
        "Error: --shard 3/3 holds no frame pairs: the selection holds 2, one for each of the first "
        "2 shards"), res.output


# -- cameras that stand still while the frames move ----------------------------------------------

def test_check_geometry_warns_when_the_cameras_stand_still_while_the_frames_differ(tmp_path):
    from fake_datasets import demo_sequence, write_fake_custom

    frames, _ = demo_sequence("street")                 # the camera moves 7-8 px per frame
    root = write_fake_custom(tmp_path / "walk", [dict(f, cam=frames[0]["cam"]) for f in frames])
    res = run("check", "--dataset", "custom", "--root", root, "--geometry")
    assert res.exit_code == 0, res.output                         # a warning, not an error
    assert "photometric check too little motion to judge" in res.output
    assert ("walk: warning: the cameras say the camera hardly moves (median predicted motion 0.00 "
            "px) while the frames differ") in res.output, res.output
    # a camera that does stand still, with frames that do not change: nothing to say
    still = write_fake_custom(tmp_path / "still", [dict(frames[0]) for _ in frames])
    res = run("check", "--dataset", "custom", "--root", still, "--geometry")
    assert res.exit_code == 0 and "warning" not in res.output, res.output


# -- KITTI: what a missing flow_occ and the testing split ask for ----------------------------------

def test_kitti_messages_name_the_files_that_make_a_pair_readable(tmp_path):
    from fake_datasets import KITTI_BASELINE, write_fake_kitti
    from weathergen.datasets import demo_pairs
    from weathergen.io.kitti_formats import write_disparity_png

    pair = demo_pairs(scenes=["street"])[1]
    fb = pair.intrinsics[0, 0].item() * KITTI_BASELINE
    # training without flow_occ: the message says what replaces it
    train = write_fake_kitti(tmp_path / "train", pair)
    (train / "flow_occ" / "000000_10.png").unlink()
    res = run("check", "--dataset", "kitti", "--root", tmp_path / "train")
    assert res.exit_code == 1
    assert ("000000: ground-truth flow file is missing (without disp_occ_1 and flow_occ, frame 11's "
            "own disparity as disp_occ_0/NNNNNN_11.png lets the pair be read: frame-2 depth from "
            "it, the camera motion from feature matching): training/flow_occ/000000_10.png") \
        in res.output.replace("\n", " "), res.output
    # the testing split: check lists exactly the two files its hint asks for
    test = write_fake_kitti(tmp_path / "test", pair, split="testing")
    res = run("check", "--dataset", "kitti", "--root", tmp_path / "test", "--split", "testing")
    assert res.exit_code == 1
    assert ("put disparities of your own as disp_occ_0/NNNNNN_10.png and disp_occ_0/NNNNNN_11.png): "
            "testing/disp_occ_0/000000_10.png, testing/disp_occ_0/000000_11.png\n") in res.output, \
        res.output
    assert "disp_occ_1" not in res.output and "flow_occ" not in res.output
    res = run("render", "--dataset", "kitti", "--root", tmp_path / "test", "--split", "testing",
              "--out", tmp_path / "o")
    assert res.exit_code == 2 and ("put disparities of your own as disp_occ_0/000000_10.png and "
                                   "disp_occ_0/000000_11.png)") in res.output, res.output
    # and following either hint makes the pair readable
    write_disparity_png(train / "disp_occ_0" / "000000_11.png", fb / pair.depth2[0].numpy())
    for path in (test / "disp_occ_0" / "000000_10.png", test / "disp_occ_0" / "000000_11.png"):
        write_disparity_png(path, fb / (pair.depth1 if path.stem.endswith("10") else pair.depth2)[0].numpy())
    for root, split in ((tmp_path / "train", "training"), (tmp_path / "test", "testing")):
        res = run("check", "--dataset", "kitti", "--root", root, "--split", split, "--fit-min-points", "30")
        assert res.exit_code == 0, res.output


# -- the right view of a stereo render gets what the left gets ------------------------------------

def test_stereo_with_format_both_writes_the_right_view_as_the_left(tmp_path, demo_root):
    import numpy as np
    import torch

    from fake_datasets import KITTI_BASELINE, demo_sequence, write_fake_kitti_stereo
    from weathergen.engine.rendering.stereo import warp_view_depth
    from weathergen.io.exr import read_exr
    from weathergen.io.images import read_image, read_raw
    from weathergen.io.sintel_formats import read_cam, read_dpt
    from weathergen.outputs import read_metadata

    _, pairs = demo_sequence("street")
    write_fake_kitti_stereo(tmp_path / "kitti", pairs[0])
    out = tmp_path / "stereo"
    res = run("render", "--dataset", "kitti", "--root", tmp_path / "kitti", "--preset", "snow-moderate",
              "--set", "far=5", "--stereo", "--format", "both", "--out", out, "-q")
    assert res.exit_code == 0, res.output
    t = out / "training"
    pair = "000004_0010"
    for side in ("", "_right"):
        for n in (10, 11):
            png = read_image(t / f"snow-moderate_clean{side}" / pair / f"frame_{n:04d}.png")
            exr = read_exr(t / f"snow-moderate_clean{side}_exr" / pair / f"frame_{n:04d}.exr")
            assert set(exr) >= {"opacity"} and exr["opacity"].max() > 0.1
            assert np.abs(exr["RGB"] - png).max() <= 0.5 / 255 + 1e-6   # the PNG is the EXR rounded
    # its depth and cameras: the left's depth warped into it, cameras moved by the baseline
    left_depth = read_dpt(t / "depth" / pair / "frame_0010.dpt")
    right_depth = read_dpt(t / "depth_right" / pair / "frame_0010.dpt")
    k_left, e_left = read_cam(t / "camdata_left" / pair / "frame_0010.cam")
    k_right, e_right = read_cam(t / "camdata_right" / pair / "frame_0011.cam")
    _, e_left2 = read_cam(t / "camdata_left" / pair / "frame_0011.cam")
    right_from_left = np.eye(4)
    right_from_left[0, 3] = -KITTI_BASELINE
    np.testing.assert_allclose(k_right, k_left)
    np.testing.assert_allclose(e_right, (right_from_left @ np.vstack([e_left2, [0, 0, 0, 1]]))[:3],
                               atol=1e-6)
    np.testing.assert_allclose(e_left, np.eye(4)[:3])       # KITTI: camera 1 is the world
    expected = warp_view_depth(torch.from_numpy(left_depth)[None], None, torch.from_numpy(k_left),
                               torch.from_numpy(right_from_left))[0][0].numpy()
    np.testing.assert_allclose(right_depth, expected, rtol=1e-6)
    # and the metadata places the right camera; the pair lists every file (resume finds them)
    meta = read_metadata(t / "particles" / pair / "frame_0010.npz")
    np.testing.assert_allclose(meta["right_from_left"], right_from_left, atol=1e-9)
    np.testing.assert_allclose(meta["right_intrinsics"], k_left)
    listed = set(json.loads(str(meta["files"])))
    assert {f"training/snow-moderate_clean_right_exr/{pair}/frame_0011.exr",
            f"training/depth_right/{pair}/frame_0011.dpt",
            f"training/depth_provenance_right/{pair}/frame_0011.png",
            f"training/camdata_right/{pair}/frame_0010.cam"} <= listed
    # the right view's classes: its holes (disoccluded, at the border) are completed, not far
    kinds = read_raw(t / "depth_provenance_right" / pair / "frame_0010.png")
    assert kinds.shape == right_depth.shape and set(np.unique(kinds)) <= {0, 1, 2}
    assert (right_depth[kinds != 2] < 1000.0).all()


# -- the progress rate counts computed pairs only ------------------------------------------------

def test_progress_rate_counts_computed_pairs_only(fake_sintel, tmp_path):
    from weathergen.execution import RunClock

    (fake_sintel / "training" / "depth" / "alley" / "frame_0001.dpt").write_bytes(b"PIEH")
    res = run("render", "--root", fake_sintel, "--scenes", "alley", "--frames-per-scene", "2",
              "--set", "count=20", "--out", tmp_path / "o")
    assert res.exit_code == 1, res.output
    progress = [line for line in res.output.splitlines() if line.startswith("[")]
    assert progress[0].startswith("[1/2 pairs] sintel/training/alley/0001 failed"), progress
    assert progress[1].startswith("[2/2 pairs, ") and " pairs/h" in progress[1], progress
    # counts read in the right number: one pair, not "1 pair(s)" or "1 pairs"
    assert "1 pair failed" in res.output and "pair(s)" not in res.output, res.output
    res = run("check", "--root", fake_sintel, "--scenes", "alley", "--frames-per-scene", "1")
    assert res.exit_code == 1 and "1 of 1 pair cannot be read." in res.output, res.output
    now = [0.0]
    clock = RunClock(3, now=lambda: now[0])
    now[0] = 1.0
    clock.add(computed=False)                # a failed pair: done in moments, not the pace
    assert clock.per_hour() is None and clock.pace() == "" and clock.time_left() == ""
    now[0] = 10.0
    clock.add()
    assert clock.per_hour() == pytest.approx(360.0) and clock.pace() == "10.0 s/pair"
    assert clock.time_left() == "10 s"


# -- inspect shows what a user reads ---------------------------------------------------------------

def test_inspect_shows_the_types_a_user_reads_beside_how_they_are_stored(tmp_path, demo_root):
    import torch

    from weathergen.engine import Particles
    from weathergen.outputs import read_metadata, write_metadata

    out = tmp_path / "o"
    res = run("render", "--scenes", "street", "--frames-per-scene", "1", "--set", "count=200",
              "--out", out, "-q")
    assert res.exit_code == 0, res.output
    meta = out / "training" / "particles" / "street_0001" / "frame_0001.npz"
    res = run("inspect", meta)
    assert res.exit_code == 0, res.output
    rows = {cells[0]: cells[1:] for cells in (
        [c.strip() for c in line.strip("│ ").split("│")] for line in res.output.splitlines()
        if line.startswith("│")) if len(cells) == 7}
    particles = Particles.load(meta)
    for name in ("position", "color", "rotation", "template"):
        dtype, shape, low, high, _, stored = rows[name]
        t = getattr(particles, name)
        assert dtype == str(t.dtype).removeprefix("torch."), (name, rows[name])
        assert shape == "×".join(map(str, t.shape))
        assert float(low) == pytest.approx(t.double().min().item(), rel=1e-3, abs=1e-6)
        assert float(high) == pytest.approx(t.double().max().item(), rel=1e-3, abs=1e-6)
    assert rows["position"][0] == "float32" and rows["position"][-1] == "uint16 grid"
    assert rows["color"][-1] == "uint8 /255" and rows["template"][0] == "int64"
    # visibility counts are stored by a render; a file without them says so, not "-1"
    assert re.search(r"visible in frame 1 / 2 +│ \d+ / \d+ ", res.output), res.output
    arrays = read_metadata(meta)
    del arrays["visible1"], arrays["visible2"]
    write_metadata(tmp_path / "unseen.npz", arrays)
    res = run("inspect", tmp_path / "unseen.npz")
    assert res.exit_code == 0, res.output
    assert "not recorded" in res.output and "-1 / -1" not in res.output
    assert particles.template.dtype == torch.int64
