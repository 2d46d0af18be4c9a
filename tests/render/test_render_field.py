"""`weathergen render` with weather-field presets: frames shared by pairs, --sequence, shards,
workers, resume, re-rendering and the particle ground truth, end to end on the demo scene."""

from __future__ import annotations

import json

import numpy as np
import torch
import pytest
from click.testing import CliRunner

from weathergen.cli.main import _register, cli
from weathergen.io.images import read_image
from weathergen.io.sintel_formats import read_flo
from run_helpers import output_digests

FIELD = ("--scenes", "street", "--frames-per-scene", "2", "--preset", "snow-light",
         "--set", "far=5")
PASS = "snow-light_clean"


def run(*args):
    _register()
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def pairs_run(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("field") / "pairs"
    res = run("render", "--out", out, "--particle-truth", *FIELD)
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def sequence_run(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("field") / "sequence"
    res = run("render", "--out", out, "--sequence", "--particle-truth", *FIELD)
    assert res.exit_code == 0, res.output
    return out


def test_pairs_of_a_scene_share_their_common_frames(pairs_run):
    frames = pairs_run / "training" / PASS
    for n in (2,):
        a = (frames / f"street_{n - 1:04d}" / f"frame_{n:04d}.png").read_bytes()
        b = (frames / f"street_{n:04d}" / f"frame_{n:04d}.png").read_bytes()
        assert a == b
    manifest = json.loads((pairs_run / "manifest.json").read_text())
    seeds = {p["seed"] for p in manifest["pairs"].values()}
    assert len(seeds) == 1            # one field (the scene's seed) for every pair of the scene
    assert manifest["preset"]["model"] == "field"
    assert manifest["outputs"]["particle_truth"] is True


def test_sequence_holds_every_frame_once_and_equals_the_pair_frames(pairs_run, sequence_run):
    frames = sequence_run / "training" / PASS / "street"
    assert sorted(p.name for p in frames.iterdir()) == [f"frame_{n:04d}.png" for n in (1, 2, 3)]
    for n in (1, 2, 3):
        pair_dir = f"street_{min(n, 2):04d}"
        same = (pairs_run / "training" / PASS / pair_dir / f"frame_{n:04d}.png").read_bytes()
        assert (frames / f"frame_{n:04d}.png").read_bytes() == same
    # the sequence reads back as a Sintel tree: consecutive frames form the pairs
    res = run("check", "--root", sequence_run, "--pass", PASS)
    assert res.exit_code == 0 and "All 2 pairs" in res.output, res.output
    for n in (1, 2):
        assert (sequence_run / "training" / "particles" / "street" / f"frame_{n:04d}.npz").is_file()
        assert (sequence_run / "training" / "depth" / "street" / f"frame_{n:04d}.dpt").is_file()
    assert (sequence_run / "training" / "depth" / "street" / "frame_0003.dpt").is_file()
    assert not (sequence_run / "training" / "particles" / "street" / "frame_0003.npz").exists()


def test_sequence_bytes_do_not_depend_on_shards_workers_or_resume(sequence_run, tmp_path):
    out = tmp_path / "sharded"
    assert run("render", "--out", out, "--sequence", "--particle-truth", "--shard", "2/2",
               *FIELD).exit_code == 0
    res = run("render", "--out", out, "--sequence", "--particle-truth", "--shard", "1/2",
              "--workers", "2", *FIELD)
    assert res.exit_code == 0, res.output
    assert output_digests(out) == output_digests(sequence_run)
    # an interrupted run: a pair lost its metadata (and the frame it writes); resume redoes it
    (out / "training" / "particles" / "street" / "frame_0002.npz").unlink()
    (out / "training" / PASS / "street" / "frame_0002.png").unlink()
    res = run("render", "--out", out, "--sequence", "--particle-truth", "--resume", "--shard",
              "2/2", *FIELD)
    assert res.exit_code == 0, res.output
    assert output_digests(out) == output_digests(sequence_run)


def test_sequence_rerenders_from_its_particles_bit_identically(sequence_run, tmp_path):
    out = tmp_path / "again"
    res = run("render", "--particles", sequence_run, "--sequence", "--scenes", "street",
              "--frames-per-scene", "2",
              "--out", out)
    assert res.exit_code == 0, res.output
    a, b = out / "training" / PASS, sequence_run / "training" / PASS
    assert output_digests(a) == output_digests(b)


def test_particle_truth_files(pairs_run):
    root = pairs_run / "training"
    flow = read_flo(root / "particle_flow" / "street_0001" / "frame_0001.flo")
    seen = read_flo(root / "seen_flow" / "street_0001" / "frame_0001.flo")
    scene = read_flo(root / "flow" / "street_0001" / "frame_0001.flo")
    opacity = read_image(root / "particle_opacity" / "street_0001" / "frame_0001.png")[..., 0]
    assert flow.shape == scene.shape == seen.shape and opacity.shape == scene.shape[:2]
    dominant = opacity >= 0.5
    assert 0 < dominant.sum() < dominant.size and (opacity > 0).sum() > dominant.sum()
    assert np.allclose(seen[dominant], flow[dominant])
    assert np.array_equal(seen[~dominant], scene[~dominant])
    assert np.abs(flow[opacity > 0]).max() > 0


def test_sequence_refuses_a_paper_preset(tmp_path, demo_root):
    out = tmp_path / "paper"
    res = run("render", "--out", out, "--sequence", "--scenes", "street", "--preset", "snow")
    assert res.exit_code == 2
    assert "weather-field preset" in res.output and "Traceback" not in res.output
    assert not out.exists()


def test_stereo_renders_kitti_image_3_with_the_same_particles(tmp_path, demo_root):
    import shutil

    from fake_datasets import demo_sequence, write_fake_kitti

    _, pairs = demo_sequence("street")
    split = write_fake_kitti(tmp_path / "kitti", pairs[0], scene="000004")
    (split / "image_3").mkdir()
    for n in (10, 11):      # the right camera's frames (their content does not matter here)
        shutil.copy(split / "image_2" / f"000004_{n}.png", split / "image_3" / f"000004_{n}.png")
    out = tmp_path / "stereo"
    res = run("render", "--dataset", "kitti", "--root", tmp_path / "kitti", "--preset",
              "snow-moderate", "--set", "far=5", "--stereo", "--particle-truth", "--out", out)
    assert res.exit_code == 0, res.output
    # the particle ground truth also in KITTI's own flow format, valid where particles are
    from weathergen.io.kitti_formats import read_flow_png

    flow, valid = read_flow_png(out / "training" / "particle_flow_occ" / "000004_0010"
                                / "frame_0010.png")
    sintel = read_flo(out / "training" / "particle_flow" / "000004_0010" / "frame_0010.flo")
    assert 0 < valid.sum() < valid.size
    assert np.allclose(flow[valid], sintel[valid], atol=1 / 64)
    # flows beyond KITTI's +-512 px (near flakes) are marked not valid there, kept in the .flo
    assert not valid[(np.abs(sintel) >= 512).any(-1)].any()
    _, seen_valid = read_flow_png(out / "training" / "seen_flow_occ" / "000004_0010"
                                  / "frame_0010.png")
    assert seen_valid.sum() > 0
    left = out / "training" / "snow-moderate_clean" / "000004_0010"
    right = out / "training" / "snow-moderate_clean_right" / "000004_0010"
    images = {}
    for side, folder in (("left", left), ("right", right)):
        for n in (10, 11):
            images[side, n] = read_image(folder / f"frame_{n:04d}.png")
    original = read_image(split / "image_3" / "000004_10.png")
    # the right frame carries weather, and not the left frame's (the particles moved by disparity)
    assert np.abs(images["right", 10] - original).max() > 0.1
    assert np.abs(images["right", 10] - images["left", 10]).max() > 0.1
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["outputs"]["stereo"] is True
    # a dataset without a second camera: each pair fails with one line naming the reason (every
    # pair failing: exit 2, nothing written)
    res = run("render", "--scenes", "street", "--frames-per-scene", "1", "--preset", "snow-light",
              "--stereo", "--out", tmp_path / "mono")
    assert res.exit_code == 2 and "no second camera" in res.output
    assert not (tmp_path / "mono").exists()


def test_stereo_reads_a_right_camera_in_the_custom_layout(tmp_path, demo_root):
    import shutil

    from fake_datasets import demo_sequence, write_fake_custom

    frames, _ = demo_sequence("street")
    root = tmp_path / "custom"
    write_fake_custom(root / "walk", frames[:2])
    right = root / "walk" / "right"
    shutil.copytree(root / "walk" / "frames", right / "frames")
    (right / "camera.json").write_text(json.dumps(
        {"right_from_left": [[1, 0, 0, -0.3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}))
    out = tmp_path / "stereo"
    res = run("render", "--dataset", "custom", "--root", root, "--preset", "snow-moderate",
              "--set", "far=5", "--stereo", "--out", out)
    assert res.exit_code == 0, res.output
    rendered = sorted((out / "training").glob("snow-moderate_*_right/walk_*/frame_*.png"))
    assert len(rendered) == 2
    (right / "camera.json").write_text("{}")
    res = run("render", "--dataset", "custom", "--root", root, "--preset", "snow-moderate",
              "--stereo", "--out", tmp_path / "bad")
    assert res.exit_code == 2 and "camera.json: not a right camera file" in res.output


def test_preview_and_evaluate_read_a_sequence_output(sequence_run):
    from weathergen.outputs import WeatherFolder
    from weathergen.render import contact_sheet

    sheet = contact_sheet(sequence_run, pairs=2, width=96)
    assert sheet.image.shape[0] > 0 and sheet.image.shape[1] == 3 * 96
    folder = WeatherFolder.open(sequence_run)
    assert folder.sequence and [p.frame for p in folder.pairs] == [1, 2]
    first, second = folder.frames(folder.pairs[0])
    again, _ = folder.frames(folder.pairs[1])
    assert torch.equal(second, again)      # frame 2 is one file, shared by both pairs


def test_stereo_sequence_on_spring_writes_every_right_frame_once(tmp_path, demo_root):
    import shutil

    from fake_datasets import demo_sequence, write_fake_spring

    frames, _ = demo_sequence("street")
    root = write_fake_spring(tmp_path / "spring", frames[:3])
    scene = root / "train" / "0001"
    (scene / "frame_right").mkdir()
    for n in (1, 2, 3):
        shutil.copy(scene / "frame_left" / f"frame_left_{n:04d}.png",
                    scene / "frame_right" / f"frame_right_{n:04d}.png")
    out = tmp_path / "out"
    res = run("render", "--dataset", "spring", "--root", root, "--split", "train", "--preset",
              "snow-moderate", "--set", "far=5", "--stereo", "--sequence", "--out", out)
    assert res.exit_code == 0, res.output
    right = out / "training" / "snow-moderate_clean_right" / "0001"
    assert sorted(p.name for p in right.iterdir()) == [f"frame_{n:04d}.png" for n in (1, 2, 3)]
    left = read_image(out / "training" / "snow-moderate_clean" / "0001" / "frame_0002.png")
    assert np.abs(read_image(right / "frame_0002.png") - left).max() > 0.1
