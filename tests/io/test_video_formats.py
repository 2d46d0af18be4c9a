"""Animated GIF (our encoder and decoder, checked against a file written byte by byte from the
format's description and against OpenCV's decoder) and the MP4 writer (read back with OpenCV)."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from weathergen.errors import ConfigError, FormatError
from gif_reader import decode_gif, read_gif
from weathergen.io.gif import encode_gif, frame_delay, palette_indices
from weathergen.io.video import write_video


def _cv2_frames(path) -> list[np.ndarray]:
    """Every frame OpenCV decodes from a video file, RGB."""
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame[..., ::-1])
    cap.release()
    return frames


def test_reads_a_gif_written_from_the_format_description(tmp_path):
    # 2x2 pixels, indices [[0, 1], [1, 0]], a global palette of 4 colours, LZW minimum code size 2:
    # codes clear(4) 0 1 1 0 end(5), 3 bits each until the table reaches 8 entries, then 4 bits;
    # packed least significant bit first: 0x44 0x02 0x05
    palette = bytes([255, 0, 0, 0, 0, 255, 0, 0, 0, 0, 0, 0])
    data = (b"GIF87a" + struct.pack("<HHBBB", 2, 2, 0x81, 0, 0) + palette
            + b"\x2c" + struct.pack("<HHHHB", 0, 0, 2, 2, 0)
            + bytes([2, 3, 0x44, 0x02, 0x05, 0]) + b"\x3b")
    path = tmp_path / "hand.gif"
    path.write_bytes(data)
    frames, delays = read_gif(path)
    red, blue = [255, 0, 0], [0, 0, 255]
    assert len(frames) == 1 and delays == [0]
    np.testing.assert_array_equal(frames[0], [[red, blue], [blue, red]])
    np.testing.assert_array_equal(_cv2_frames(path)[0], frames[0])    # OpenCV reads it alike


def test_few_colours_round_trip_exactly_through_both_decoders(tmp_path):
    rng = np.random.default_rng(0)
    colours = rng.integers(0, 256, (200, 3)).astype(np.uint8)
    noise = colours[rng.integers(0, 200, (120, 161))]        # fills the 4096-code table often
    halves = np.zeros((120, 161, 3), np.uint8)
    halves[:, :80] = 255
    stripes = np.repeat((np.arange(161) % 7 * 30).astype(np.uint8)[None, :, None], 120, 0).repeat(3, 2)
    frames = [noise, halves, stripes]
    path = tmp_path / "a.gif"
    path.write_bytes(encode_gif(frames, 10))
    back, delays = read_gif(path)
    assert delays == [10, 10, 10]
    for want, ours, theirs in zip(frames, back, _cv2_frames(path), strict=True):
        np.testing.assert_array_equal(ours, want)
        np.testing.assert_array_equal(theirs, want)


@pytest.mark.parametrize("length", [*range(250, 262), *range(505, 518), *range(1020, 1030), 4200, 9000])
def test_code_width_changes_and_table_resets_at_every_length(tmp_path, length):
    # one row of distinct-looking pixels gives about one code per pixel: the stream ends just
    # before, at or after the points where the code width grows (9 -> 10 -> 11 bits) or the table
    # is cleared, where an encoder and a decoder disagree first
    rng = np.random.default_rng(length)
    row = rng.integers(0, 256, (1, length)).astype(np.uint8)
    rgb = np.stack((row, 255 - row, row // 2), -1)
    path = tmp_path / "row.gif"
    path.write_bytes(encode_gif([rgb], 24))
    np.testing.assert_array_equal(read_gif(path)[0][0], rgb)
    np.testing.assert_array_equal(_cv2_frames(path)[0], rgb)


def test_a_photograph_keeps_its_colours_closely(demo_root):
    from weathergen.io.images import read_raw

    rgb = read_raw(demo_root / "training" / "clean" / "street" / "frame_0001.png")[..., ::-1]
    assert len(np.unique(rgb.reshape(-1, 3), axis=0)) > 256      # needs a reduced palette
    palette, indices = palette_indices(rgb)
    error = np.abs(palette[indices].astype(int) - rgb)
    assert error.mean() < 3 and error.max() <= 16
    back, _ = decode_gif(encode_gif([rgb], 24))
    np.testing.assert_array_equal(back[0], palette[indices])


def test_frame_delays_keep_the_frame_rate():
    """Each frame starts at the hundredth nearest to its time: 24 fps alternates 4 and 5
    hundredths, 24 frames last one second (a constant 4 would play at 25 fps)."""
    delays = [frame_delay(24, i) for i in range(48)]
    assert delays[:6] == [4, 4, 5, 4, 4, 4] and sum(delays) == 200
    assert all(abs(sum(delays[:k]) - 100 * k / 24) <= 0.5 for k in range(49))
    assert {frame_delay(10, i) for i in range(30)} == {10} and frame_delay(25, 7) == 4
    assert frame_delay(1000, 3) == 1                # never 0 (viewers would pick their own)
    frames = [np.full((2, 2, 3), i, np.uint8) for i in range(24)]
    assert sum(decode_gif(encode_gif(frames, 24))[1]) == 100


def test_encoder_and_decoder_refuse_what_they_cannot_do(tmp_path):
    with pytest.raises(ValueError, match="at least one frame"):
        encode_gif([], 24)
    with pytest.raises(ValueError, match="share one size"):
        encode_gif([np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5, 3), np.uint8)], 24)
    with pytest.raises(FormatError, match="not a GIF file"):
        decode_gif(b"\x89PNG\r\n\x1a\n" + bytes(20), tmp_path / "x.gif")
    data = encode_gif([np.zeros((4, 4, 3), np.uint8)], 24)
    with pytest.raises(FormatError, match="truncated GIF"):
        decode_gif(data[:-6], tmp_path / "x.gif")


@pytest.mark.parametrize("suffix", [".mp4", ".gif"])
def test_write_video_reads_back_with_opencv(tmp_path, suffix):
    # odd sizes: MP4 frames are padded to even ones, GIF keeps them
    frames = [np.full((31, 45, 3), (40 * i, 200 - 40 * i, 90), np.uint8) for i in range(4)]
    path = tmp_path / f"v{suffix}"
    assert write_video(path, iter(frames), fps=10) == 4
    back = _cv2_frames(path)
    assert len(back) == 4
    h, w = (32, 46) if suffix == ".mp4" else (31, 45)
    assert all(f.shape == (h, w, 3) for f in back)
    cap = cv2.VideoCapture(str(path))
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(10)
    cap.release()
    for i, got in enumerate(back):      # lossy (mp4v), but each frame is nearest to its own
        errors = [np.abs(got[:31, :45].astype(int) - want).mean() for want in frames]
        assert int(np.argmin(errors)) == i and errors[i] < 4
    assert [p.name for p in tmp_path.iterdir()] == [path.name]           # no temporary left


def test_write_video_leaves_no_file_when_a_frame_fails(tmp_path):
    def frames():
        yield np.zeros((16, 16, 3), np.uint8)
        yield np.zeros((16, 16, 3), np.uint8)
        raise RuntimeError("the third frame could not be made")

    for suffix in (".mp4", ".gif"):
        with pytest.raises(RuntimeError, match="third frame"):
            write_video(tmp_path / f"v{suffix}", frames(), fps=24)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ConfigError, match="unknown video format '.avi'"):
        write_video(tmp_path / "v.avi", frames(), fps=24)


# -- an MP4 is checked before it gets its name ---------------------------------------------------

def _frames(n, h=31, w=45):
    return [np.full((h, w, 3), 7 * i, np.uint8) for i in range(n)]


def test_a_complete_mp4_passes_its_check_and_a_cut_one_does_not(tmp_path):
    import errno

    from weathergen.io.video import check_mp4

    path = tmp_path / "a.mp4"
    assert write_video(path, _frames(9), 10) == 9
    check_mp4(path, 9)                                   # boxes, index and frame count agree
    with pytest.raises(OSError, match="its index counts \\[9\\] frames, not 10"):
        check_mp4(path, 10)
    data = path.read_bytes()
    for cut in (len(data) - 1, len(data) // 2, 40):
        (tmp_path / "cut.mp4").write_bytes(data[:cut])
        with pytest.raises(OSError) as caught:
            check_mp4(tmp_path / "cut.mp4", 9, "named.mp4")
        assert caught.value.errno in (errno.EIO, errno.ENOSPC)
        assert caught.value.filename == "named.mp4"
        assert "the video is incomplete" in caught.value.strerror


def _box(kind: str, payload: bytes = b"", large: bool = False) -> bytes:
    """An ISO-BMFF box: 32-bit size and type, or size 1 and a 64-bit size after the type."""
    if large:
        return (1).to_bytes(4, "big") + kind.encode() + (16 + len(payload)).to_bytes(8, "big") \
            + payload
    return (8 + len(payload)).to_bytes(4, "big") + kind.encode() + payload


def _index(frames: int) -> bytes:
    """A moov box with one track whose stsz (version/flags, sample size 0, count) counts
    ``frames`` samples."""
    stsz = _box("stsz", bytes(4) + bytes(4) + frames.to_bytes(4, "big") + bytes(4 * frames))
    return _box("moov", _box("mvhd", bytes(100)) + _box("trak", _box("mdia", _box("minf", _box(
        "stbl", _box("stsd", bytes(8)) + stsz)))))


def test_check_mp4_reads_the_boxes_as_written_by_hand(tmp_path):
    """Files built box by box: the index before or after the data, a 64-bit box size, a last box
    of size 0 (to the end of the file) pass; a missing index, a box running past the end, a
    wrong count and trailing bytes are refused, each saying what is wrong."""
    from weathergen.io.video import check_mp4

    ftyp = _box("ftyp", b"isom" + bytes(4) + b"isommp41")
    good = {
        "index last": ftyp + _box("mdat", bytes(50)) + _index(3),
        "index first": ftyp + _index(3) + _box("mdat", bytes(50)),
        "64-bit data": ftyp + _box("mdat", bytes(50), large=True) + _index(3),
        "data to the end": ftyp + _index(3) + (0).to_bytes(4, "big") + b"mdat" + bytes(50),
    }
    for data in good.values():
        (tmp_path / "a.mp4").write_bytes(data)
        check_mp4(tmp_path / "a.mp4", 3)
    head = ftyp + _box("mdat", bytes(50))                   # 24 + 58 bytes
    bad = {
        "no index": (head, "no moov box (82 bytes written)"),
        "cut in the index": ((head + _index(3))[:-5], "its boxes end at byte 82 of "),
        "another count": (head + _index(2), "its index counts [2] frames, not 3"),
        "trailing bytes": (head + _index(3) + b"xyz", "(truncated)"),
    }
    for name, (data, problem) in bad.items():
        (tmp_path / "a.mp4").write_bytes(data)
        with pytest.raises(OSError) as caught:
            check_mp4(tmp_path / "a.mp4", 3)
        assert problem in caught.value.strerror, (name, caught.value.strerror)


def test_the_next_write_removes_the_temporary_of_a_killed_writer_only(tmp_path):
    """A temporary of a writer that is gone (its pid in its name) is removed; one of a writer
    that runs (this process) stays, and so does a file that is no temporary of the video."""
    import os

    dead = subprocess_pid()
    gone = tmp_path / f".v.mp4.{dead}.abcd1234.mp4"
    mine = tmp_path / f".v.mp4.{os.getpid()}.efgh5678.mp4"
    other = tmp_path / ".v.mp4.notes.txt"
    for p in (gone, mine, other):
        p.write_bytes(b"x")
    write_video(tmp_path / "v.mp4", _frames(2), 10)
    assert not gone.exists() and mine.exists() and other.exists()


def subprocess_pid() -> int:
    """The pid of a process that has ended."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid
