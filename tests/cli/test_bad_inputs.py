"""Bad inputs end in one line naming the file or option, a non-zero exit and no traceback; inputs
that do not fit together (stored particles of another preset or dataset, a scale for a scene that
is not there, an empty scene folder) are reported instead of silently ignored."""

from __future__ import annotations

import errno
import json
import shutil

import numpy as np
import pytest

from weathergen.outputs import read_metadata, write_metadata
from run_helpers import cli_run as run, one_line_error

FAST = ("--scenes", "street", "--frames-per-scene", "2", "--set", "count=300")
NOT_UTF8 = b"count = 3\n\xff\xfe\x00binary\x89PNG\n"




@pytest.fixture(scope="module")
def snow_run(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("render") / "snow"
    res = run("render", "--out", out, "-q", *FAST)
    assert res.exit_code == 0, res.output
    return out


# -- files that are not text --------------------------------------------------------------------

def test_binary_preset_file_is_one_line(tmp_path):
    bad = tmp_path / "mine.toml"
    bad.write_bytes(NOT_UTF8)
    line = one_line_error(run("render", "--preset-file", bad, "--out", tmp_path / "o", *FAST[:4]))
    assert str(bad) in line and "not UTF-8 text" in line and "preset" in line
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name,content,message", [
    ("scales.toml", NOT_UTF8, "not UTF-8 text"),
    ("scales.json", b"[0.5, 2.0]", "expected a table of scene = factor entries"),
    ("scales.toml", b"street = 2.0\nstreeet = 0.5\n", "no scene named streeet"),
], ids=["binary", "json-list", "unknown-scene"])
def test_bad_scene_scales_are_one_line(tmp_path, name, content, message):
    table = tmp_path / name
    table.write_bytes(content)
    for command in (("render", "--out", tmp_path / "o", *FAST), ("check",)):
        line = one_line_error(run(*command, "--scene-scales", table))
        assert str(table) in line and message in line
    assert not (tmp_path / "o").exists()


def test_scene_scales_for_scenes_left_out_by_the_selection_are_fine(tmp_path):
    table = tmp_path / "scales.toml"
    table.write_text("street = 2.0\ncourtyard = 0.5\n")
    res = run("check", "--scenes", "street", "--scene-scales", table)
    assert res.exit_code == 0, res.output


def test_sintel_scene_folder_without_frames_is_reported(fake_sintel, tmp_path):
    empty = fake_sintel / "training/clean/cave_2"
    empty.mkdir()
    (fake_sintel / "training/clean/.cache").mkdir()          # hidden folders are not scenes
    for command in (("render", "--out", tmp_path / "o", "--set", "count=20"), ("check",)):
        line = one_line_error(run(*command, "--root", fake_sintel))
        assert str(empty) in line and "no frame pair" in line and "no frame_NNNN.png" in line
    assert not (tmp_path / "o").exists()
    shutil.copy(fake_sintel / "training/clean/alley/frame_0001.png", empty / "frame_0001.png")
    assert "only frame 1" in one_line_error(run("check", "--root", fake_sintel))
    # left out by the selection, it is no obstacle
    res = run("check", "--root", fake_sintel, "--scenes", "alley,bamboo")
    assert res.exit_code == 0, res.output


# -- writing where one cannot -------------------------------------------------------------------

def test_preview_into_a_read_only_place_is_one_line(snow_run, tmp_path, monkeypatch):
    import weathergen.io.atomic as atomic

    def read_only(suffix="", prefix="", dir=None):
        # what mkstemp raises on a read-only file system: it names the temporary file
        raise OSError(errno.EROFS, "Read-only file system", f"{dir}/{prefix}abc123{suffix}")

    monkeypatch.setattr(atomic.tempfile, "mkstemp", read_only)
    target = tmp_path / "ro" / "sheet.png"
    line = one_line_error(run("preview", snow_run, "--out", target, "--width", "64"))
    assert f"{target}: cannot write (Read-only file system)" in line
    assert ".tmp" not in line and "abc123" not in line


def test_preview_where_a_file_blocks_the_folder_is_one_line(snow_run, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    line = one_line_error(run("preview", snow_run, "--out", blocker / "sheet.png", "--width", "64"))
    assert str(blocker) in line and "cannot write" in line


def test_contact_sheet_says_when_it_shows_only_some_pairs(snow_run, tmp_path):
    from weathergen.io.images import read_image

    out = tmp_path / "one.png"
    res = run("preview", snow_run, "--out", out, "--width", "64", "--pairs", "1")
    assert res.exit_code == 0, res.output
    assert "Preview of 1 of 2 pairs" in res.output and "--pairs 2 shows all" in res.output
    partial = read_image(out)
    res = run("preview", snow_run, "--out", tmp_path / "all.png", "--width", "64", "--pairs", "2")
    assert res.exit_code == 0 and "Preview of 2 pairs" in res.output, res.output
    full = read_image(tmp_path / "all.png")
    row = full.shape[0] // 2
    # the partial sheet is one row plus a footer line of text, not two rows
    assert row < partial.shape[0] < 2 * row
    footer = partial[row:]
    assert footer.max() > 0.9 and np.median(footer) < 0.2


def test_text_file_as_checkpoint_says_what_it_is(snow_run, tmp_path):
    from weathergen.errors import FormatError
    from weathergen.models.checkpoints import read_state_dict

    notes = tmp_path / "raft-small.pth"
    notes.write_text("hello, these are my notes\n")
    with pytest.raises(FormatError) as info:
        read_state_dict(notes)
    message = str(info.value)
    assert message.startswith(str(notes)) and "not a PyTorch checkpoint" in message
    assert "a text file (it starts with 'hello, these are my note')" in message
    (tmp_path / "empty.pth").write_bytes(b"")
    with pytest.raises(FormatError, match="is empty"):
        read_state_dict(tmp_path / "empty.pth")
    line = one_line_error(run("evaluate", "--model", "raft-small", "--checkpoint", notes,
                              "--weather", snow_run))
    assert "a text file" in line


# -- re-rendering stored particles --------------------------------------------------------------

def _edit_metadata(path, **changes):
    arrays = read_metadata(path)
    arrays.update({k: np.array(v) for k, v in changes.items()})
    write_metadata(path, arrays)


@pytest.mark.parametrize("change,message", [
    ({"preset_name": "rain"}, "particles of preset 'rain', but the folder's manifest says 'snow'"),
    ({"pair_dataset": "sintel"}, "metadata belongs to the training split of dataset 'sintel', not to the "
                                 "training split of 'demo'"),
    ("count", "particles sampled with other preset settings than the folder's manifest records (count)"),
], ids=["preset-name", "dataset", "preset-settings"])
def test_particles_of_another_preset_or_dataset_are_refused(snow_run, tmp_path, change, message):
    src = tmp_path / "src"
    shutil.copytree(snow_run, src)
    meta = src / "training/particles/street_0002/frame_0002.npz"
    if change == "count":
        preset = json.loads(str(read_metadata(meta)["preset"]))
        change = {"preset": json.dumps({**preset, "count": 999}, sort_keys=True)}
    _edit_metadata(meta, **change)
    out = tmp_path / "o"
    res = run("render", "--out", out, "--particles", src, *FAST[:4])
    assert res.exit_code == 1, res.output
    assert f"failed demo/training/street/0002: {meta}: {message}" in " ".join(res.output.split()), res.output
    assert not (out / "training/particles/street_0002").exists()
    assert (out / "training/particles/street_0001/frame_0001.npz").exists()


def test_changing_appearance_on_rerender_is_still_accepted(snow_run, tmp_path):
    res = run("render", "--out", tmp_path / "o", "--particles", snow_run, "--set", "blend=alpha",
              *FAST[:4])
    assert res.exit_code == 0, res.output
