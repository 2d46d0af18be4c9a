"""The .dpt / .cam / .flo readers against files written byte by byte from the documented format."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from weathergen.errors import FormatError
from weathergen.io.sintel_formats import read_cam, read_dpt, read_flo, write_cam, write_dpt, write_flo

TAG = 202021.25


def test_read_dpt_from_documented_bytes(tmp_path):
    w, h = 3, 2
    values = [1.0, 2.0, 3.0, 4.5, 5.5, 6.5]
    path = tmp_path / "d.dpt"
    path.write_bytes(struct.pack("<fii", TAG, w, h) + struct.pack("<6f", *values))
    depth = read_dpt(path)
    assert depth.shape == (2, 3)
    assert depth.dtype == np.float32
    np.testing.assert_array_equal(depth, [[1, 2, 3], [4.5, 5.5, 6.5]])  # row-major


def test_read_flo_interleaved_uv(tmp_path):
    w, h = 2, 1
    path = tmp_path / "f.flo"
    path.write_bytes(b"PIEH" + struct.pack("<ii", w, h) + struct.pack("<4f", 1.0, -2.0, 3.0, -4.0))
    flow = read_flo(path)
    assert flow.shape == (1, 2, 2)
    np.testing.assert_array_equal(flow[0, :, 0], [1.0, 3.0])   # u
    np.testing.assert_array_equal(flow[0, :, 1], [-2.0, -4.0])  # v


def test_read_cam_layout(tmp_path):
    k = np.arange(9, dtype=np.float64).reshape(3, 3) + 1
    e = np.arange(12, dtype=np.float64).reshape(3, 4) * 0.5
    path = tmp_path / "c.cam"
    path.write_bytes(struct.pack("<f", TAG) + struct.pack("<9d", *k.ravel()) + struct.pack("<12d", *e.ravel()))
    k2, e2 = read_cam(path)
    np.testing.assert_array_equal(k2, k)
    np.testing.assert_array_equal(e2, e)


@pytest.mark.parametrize("writer,reader,shape", [
    (write_dpt, read_dpt, (5, 7)),
    (write_flo, read_flo, (5, 7, 2)),
])
def test_round_trip(tmp_path, writer, reader, shape):
    arr = np.random.default_rng(1).standard_normal(shape).astype(np.float32)
    path = writer(tmp_path / "x.bin", arr)
    np.testing.assert_array_equal(reader(path), arr)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporary file left behind"


def test_cam_round_trip(tmp_path):
    k = np.array([[500.0, 0, 320], [0, 510, 240], [0, 0, 1]])
    e = np.hstack([np.eye(3), [[1.0], [2.0], [3.0]]])
    k2, e2 = read_cam(write_cam(tmp_path / "a.cam", k, e))
    np.testing.assert_array_equal(k2, k)
    np.testing.assert_array_equal(e2, e)


@pytest.mark.parametrize("reader,payload,match", [
    (read_dpt, struct.pack("<fii", 1.0, 2, 2) + b"\0" * 16, "bad header tag"),
    (read_dpt, struct.pack("<fii", TAG, 2, 2) + b"\0" * 12, "truncated"),
    (read_dpt, struct.pack("<fii", TAG, 2, 2) + b"\0" * 20, "trailing bytes"),
    (read_dpt, struct.pack("<fii", TAG, -3, 2), "implausible size"),
    (read_dpt, b"\0\0", "truncated"),
    (read_flo, struct.pack("<fii", TAG, 2, 2) + b"\0" * 16, "truncated"),
    (read_cam, struct.pack("<f", TAG) + b"\0" * 100, "truncated"),
    (read_cam, struct.pack("<f", 3.0) + b"\0" * 168, "bad header tag"),
])
def test_corrupt_files_name_the_file(tmp_path, reader, payload, match):
    path = tmp_path / "broken.bin"
    path.write_bytes(payload)
    with pytest.raises(FormatError, match=match) as info:
        reader(path)
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(FormatError, match="file not found"):
        read_dpt(tmp_path / "nope.dpt")


def test_cam_rejects_non_finite_and_bad_focal(tmp_path):
    k = np.eye(3)
    e = np.zeros((3, 4))
    e[0, 0] = np.nan
    with pytest.raises(FormatError, match="non-finite"):
        read_cam(write_cam(tmp_path / "n.cam", k, e))
    k[0, 0] = -1
    with pytest.raises(FormatError, match="focal"):
        read_cam(write_cam(tmp_path / "f.cam", k, np.zeros((3, 4))))


def test_atomic_writes_leave_no_partial_file_and_ordinary_permissions(tmp_path):
    import os

    from weathergen.io.atomic import UMASK, atomic_open
    from weathergen.io.exr import write_exr

    path = write_dpt(tmp_path / "d.dpt", np.ones((2, 3), np.float32))
    exr = write_exr(tmp_path / "f.exr", np.zeros((2, 3, 3)), {"opacity": np.zeros((2, 3))})
    for p in (path, exr):
        # a temporary file is owner-only; the written file must not inherit that
        assert os.stat(p).st_mode & 0o777 == 0o666 & ~UMASK
    with pytest.raises(KeyboardInterrupt):
        with atomic_open(tmp_path / "half.bin") as f:
            f.write(b"x" * 100)
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.dpt", "f.exr"]
