"""`weathergen preview OUT --video`: a sequence output played in order (again, until the video
lasts two seconds), an output of pairs alternating frame 1 / frame 2 at a calm rate, side by side
with the input and the opacity, read back with OpenCV; progress lines on a long video; bad inputs
as one line, exit 2 and no file."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from gif_reader import read_gif
from weathergen.io.images import read_image, read_raw, to_uint8
from weathergen.outputs import read_manifest
from weathergen.render import output_frame_rate, video_preview
from weathergen.render.video import MIN_SECONDS, PAIR_FPS
from run_helpers import cli_run as run, one_line_error

pytestmark = pytest.mark.slow

SEQUENCE = ("--scenes", "street", "--preset", "snow-light", "--set", "far=5", "--set", "snow_rate=0",
            "--sequence")   # no veil: the opacity panel is the particles' own
PAIRS = ("--scenes", "street", "--frames-per-scene", "2", "--set", "count=300")




def cv2_frames(path) -> tuple[list[np.ndarray], float]:
    """Every frame OpenCV decodes (RGB) and the frame rate it reads."""
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS)
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame[..., ::-1])
    cap.release()
    return frames, fps


def nearest(frame: np.ndarray, candidates: list[np.ndarray]) -> int:
    return int(np.argmin([np.abs(frame.astype(int) - c.astype(int)).mean() for c in candidates]))


@pytest.fixture(scope="module")
def sequence_run(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("video") / "sequence"
    res = run("render", "--out", out, "-q", "--particle-truth", *SEQUENCE)
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def pairs_run(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("video") / "pairs"
    res = run("render", "--out", out, "-q", *PAIRS)
    assert res.exit_code == 0, res.output
    return out


def sequence_frames(root) -> list[np.ndarray]:
    folder = root / "training" / "snow-light_clean" / "street"
    return [read_raw(folder / f"frame_{n:04d}.png")[..., ::-1] for n in (1, 2, 3, 4)]


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_a_four_frame_sequence_plays_in_order_until_it_lasts_two_seconds(sequence_run, tmp_path,
                                                                         suffix):
    video = tmp_path / f"street{suffix}"
    res = run("preview", sequence_run, "--video", video, "--no-captions")
    assert res.exit_code == 0, res.output
    # 4 frames at 24 fps last a sixth of a second: played 12 times, 2 s
    assert MIN_SECONDS == 2
    assert ("48 frames of 384x176 at 24 fps (2.0 s: its 4 frames played 12 times to last at "
            "least 2 s)") in res.output
    frames, fps = cv2_frames(video)
    assert len(frames) == 48 and all(f.shape == (176, 384, 3) for f in frames)
    assert fps == pytest.approx(24 if suffix == ".mp4" else 25)     # OpenCV: the first GIF delay
    want = sequence_frames(sequence_run)
    assert [nearest(f, want) for f in frames] == [0, 1, 2, 3] * 12
    if suffix == ".gif":
        ours, delays = read_gif(video)
        # whole 1/100 s, 24 fps on average: 24 frames take a second, 48 two
        assert delays[:4] == [4, 4, 5, 4] and delays[:24] == delays[24:] and sum(delays) == 200
        for a, b, w in zip(ours, frames, want):
            np.testing.assert_array_equal(a, b)          # our decoder and OpenCV's agree
            assert np.abs(a.astype(int) - w).mean() < 3    # 256 colours of each frame
    assert sorted(p.name for p in tmp_path.iterdir()) == [video.name]


def test_pairs_alternate_frame_1_and_frame_2_at_a_calm_rate(pairs_run, tmp_path):
    video = tmp_path / "pairs.gif"
    res = run("preview", pairs_run, "--video", video, "--cycles", "3", "--no-captions")
    assert res.exit_code == 0, res.output
    frames, _ = cv2_frames(video)
    assert len(frames) == 2 * 3 * 2                     # pairs x cycles x (frame 1, frame 2)
    folder = pairs_run / "training" / "snow_clean"
    want = [read_raw(folder / f"street_{p:04d}" / f"frame_{p + i:04d}.png")[..., ::-1]
            for p in (1, 2) for i in (0, 1)]
    assert [nearest(f, want) for f in frames] == [0, 1, 0, 1, 0, 1, 2, 3, 2, 3, 2, 3]
    # each frame held half a second, not a 12 Hz strobe
    assert PAIR_FPS == 2 and read_gif(video)[1] == [50] * 12
    assert "at 2 fps (6.0 s)" in res.output
    # by default each pair plays for two seconds: frame 1 / frame 2 twice
    plan = video_preview(pairs_run)
    assert len(plan.shots) == 2 * 2 * 2 and plan.fps == 2 and plan.loops == 1
    assert plan.seconds == 4
    # one pair shown once lasts a second: played twice, to last two seconds
    short = video_preview(pairs_run, pairs=1, cycles=1)
    assert (short.count, short.loops, short.seconds) == (4, 2, 2.0)


def test_side_by_side_with_the_input_and_the_opacity(sequence_run, tmp_path):
    from weathergen.datasets import open_dataset

    plan = video_preview(sequence_run, with_input=True, with_opacity=True, captions=False)
    frames = list(plan.frames())
    assert plan.size == (3 * 384, 176) and len(frames) == 48 and plan.loops == 12
    for i, frame in enumerate(frames[4:], 4):       # the loops repeat the first four frames
        np.testing.assert_array_equal(frame, frames[i % 4])
    ds = open_dataset("demo", scenes=["street"])
    pairs = [ds.load(ref) for ref in ds.pairs()]
    clean = [to_uint8(p.image1.permute(1, 2, 0).numpy()) for p in pairs]
    clean.append(to_uint8(pairs[-1].image2.permute(1, 2, 0).numpy()))
    for n, (frame, weather) in enumerate(zip(frames, sequence_frames(sequence_run)), 1):
        np.testing.assert_array_equal(frame[:, :384], clean[n - 1])
        np.testing.assert_array_equal(frame[:, 384:768], weather)
        if n < 4:   # the particle opacity of each pair's frame 1, as --particle-truth wrote it
            truth = read_raw(sequence_run / "training" / "particle_opacity" / "street"
                             / f"frame_{n:04d}.png") / 65535.0
            assert np.abs(frame[:, 768:, 0].astype(int) - to_uint8(truth)).max() <= 1
            assert frame[:, 768:, 0].max() > 100          # there is snow to see
    # written, it is three tiles wide
    video = tmp_path / "side.mp4"
    res = run("preview", sequence_run, "--video", video, "--with-input", "--with-opacity",
              "--width", "128")
    assert res.exit_code == 0, res.output
    back, _ = cv2_frames(video)
    # tiles 128 x round(176 * 128 / 384) = 128 x 59; MP4 pads the height to 60
    assert len(back) == 48 and back[0].shape == (60, 384, 3)


def test_frame_rate_comes_from_the_dataset_or_the_preset(sequence_run, pairs_run, tmp_path):
    assert output_frame_rate(read_manifest(sequence_run, "preview")) == 24
    copy = tmp_path / "kitti-like"
    shutil.copytree(pairs_run, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["input"]["dataset"] = "kitti"
    (copy / "manifest.json").write_text(json.dumps(manifest))
    assert output_frame_rate(read_manifest(copy, "preview")) == 10
    manifest["preset"].update(model="field", frame_rate=30.0)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    assert output_frame_rate(read_manifest(copy, "preview")) == 30
    video = tmp_path / "slow.mp4"
    res = run("preview", sequence_run, "--video", video, "--fps", "5")
    assert res.exit_code == 0 and "12 frames of 384x176 at 5 fps (2.4 s: its 4 frames played 3 " \
        "times" in res.output
    assert cv2_frames(video)[1] == pytest.approx(5)


def test_the_contact_sheet_stays_the_default(pairs_run):
    res = run("preview", pairs_run)
    assert res.exit_code == 0, res.output
    assert read_image(pairs_run / "preview.png").shape[1] == 3 * 480


@pytest.mark.parametrize("args,message", [
    (("--video", "{tmp}/v.avi"), "--video {tmp}/v.avi: unknown video format '.avi'; use .mp4 or .gif"),
    (("--video", "{tmp}/v"), "unknown video format '(no extension)'"),
    (("--video", "{tmp}/file/v.mp4"), "{tmp}/file: cannot write"),
    (("--video", "{tmp}/v.mp4", "--out", "{tmp}/s.png"), "--out names the contact sheet"),
    (("--with-opacity",), "--with-opacity applies to --video only"),
    (("--video", "{tmp}/v.gif", "--cycles", "2"), "--cycles applies to outputs of pairs"),
], ids=["extension", "no-extension", "parent-is-a-file", "out-and-video", "flag-without-video",
        "cycles-of-a-sequence"])
def test_bad_options_are_one_line_and_write_nothing(sequence_run, tmp_path, args, message):
    (tmp_path / "file").write_text("a file, not a folder")
    line = one_line_error(run("preview", sequence_run,
                              *[a.format(tmp=tmp_path) for a in args]))
    assert message.format(tmp=tmp_path) in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_a_folder_that_is_not_a_render_output(tmp_path):
    (tmp_path / "photos").mkdir()
    line = one_line_error(run("preview", tmp_path / "photos", "--video", tmp_path / "v.mp4"))
    assert "preview takes the folder of a render output" in line
    assert not (tmp_path / "v.mp4").exists()


def test_an_input_that_changed_mid_video_leaves_no_file(sequence_run, tmp_path):
    # the recorded input now holds the scene's first pair only: the video fails at its second frame
    copy = tmp_path / "changed"
    shutil.copytree(sequence_run, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["input"]["frames_per_scene"] = 1
    (copy / "manifest.json").write_text(json.dumps(manifest))
    video = tmp_path / "out" / "v.mp4"
    line = one_line_error(run("preview", copy, "--video", video, "--with-input"))
    assert "the recorded input has no pair demo/training/street/0002" in line
    assert not video.parent.exists() or list(video.parent.iterdir()) == []


@pytest.fixture(scope="module")
def lp_run(tmp_path_factory, demo_root, raft_small_weights):
    """An Lp attack's output: a render folder whose pairs store no particles."""
    out = tmp_path_factory.mktemp("video") / "ifgsm"
    res = run("attack", "--method", "ifgsm", "--model", "raft-small", "--checkpoint",
              raft_small_weights, "--iters", "1", "--steps", "1", "--scenes", "street",
              "--frames-per-scene", "1", "--out", out, "-q")
    assert res.exit_code == 0, res.output
    return out


def test_an_lp_attack_output_plays_and_has_no_opacity_to_show(lp_run, tmp_path):
    """An Lp attack perturbs the frames and stores no particles: its video and contact sheet show
    the frames; asking for the particles' opacity is one line, not a traceback."""
    video = tmp_path / "lp.gif"
    res = run("preview", lp_run, "--video", video, "--with-input", "--cycles", "1")
    assert res.exit_code == 0, res.output
    frames, _ = read_gif(video)
    assert len(frames) == 4 and frames[0].shape == (176, 2 * 384, 3)      # 1 s, played twice
    perturbed = read_raw(lp_run / "training" / "ifgsm_clean" / "street_0001" / "frame_0001.png")
    assert np.abs(frames[0][:, 384:].astype(int) - perturbed[..., ::-1].astype(int)).mean() < 3
    line = one_line_error(run("preview", lp_run, "--video", tmp_path / "o.mp4", "--with-opacity"))
    assert f"--with-opacity: {lp_run} holds no particles to show" in line
    assert not (tmp_path / "o.mp4").exists()
    sheet = run("preview", lp_run, "--out", tmp_path / "sheet.png")
    assert sheet.exit_code == 0, sheet.output
    image = read_image(tmp_path / "sheet.png")
    assert image.shape[1] == 3 * 480 and image[40:, 2 * 480:].max() == 0   # no opacity anywhere


def test_a_long_video_says_how_far_it_is():
    """Progress lines: one every few seconds of work, none for a video made sooner, none at the
    end (the summary line follows)."""
    from weathergen.cli.inspect_cmd import ProgressLines

    now = [0.0]
    lines = []
    progress = ProgressLines(every=5.0, clock=lambda: now[0])
    import click

    echo, click.echo = click.echo, lambda text, err=False: lines.append((text, err))
    try:
        for done in range(1, 145):
            now[0] = done * 0.25                # a quarter second a frame: 36 s for 144 frames
            progress(done, 144)
    finally:
        click.echo = echo
    assert [t for t, _ in lines] == [f"  video: {n} of 144 frames ({n // 4} s)"
                                     for n in range(20, 144, 20)]
    assert all(err for _, err in lines)
