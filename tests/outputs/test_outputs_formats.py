"""The formats of the weather frames (weathergen/outputs/formats/): each writes a pair's frames
and reads them back through PairOutput, `both` writes every registered format in order, and a new
format is one module and one line of the registry."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from engine_scenes import plane_pair
from weathergen.framepair import PairId
from weathergen.engine import load_preset, sample_particles
from weathergen.outputs import FORMATS, PairOutput, pair_metadata, read_metadata, write_pair_outputs
from weathergen.outputs import formats
from weathergen.outputs.formats import FrameFormat, formats_of, read_format

PAIR = PairId("sintel", "training", "alley_1", 3)


def _frames(h: int = 12, w: int = 16):
    rng = np.random.default_rng(0)
    frames = tuple(rng.random((h, w, 3)).astype(np.float32) for _ in range(2))
    opacity = tuple(rng.random((h, w)).astype(np.float32) for _ in range(2))
    return frames, opacity


def _write(root: Path, fmt: str):
    out = PairOutput.of(root, PAIR, "snow_clean", fmt, geometry=False)
    frames, opacity = _frames()
    pair, preset = plane_pair(12, 16), load_preset("snow")
    meta = pair_metadata(sample_particles(pair, preset, seed=0), PAIR, 1, preset.to_dict(), "snow")
    written = write_pair_outputs(out, pair, frames, opacity, meta)
    return out, written, frames, opacity


def test_the_registry_lists_png_then_exr_and_both_writes_them_in_that_order():
    assert FORMATS == ("png", "exr", "both")
    assert [f.name for f in formats_of("both")] == ["png", "exr"]
    assert read_format("both").name == "png" and read_format("exr").name == "exr"
    with pytest.raises(ValueError, match="unknown frame format 'tiff'"):
        formats_of("tiff")


@pytest.mark.parametrize("fmt", ["png", "exr", "both"])
def test_a_pair_written_in_each_format_reads_back_through_its_output(tmp_path, fmt):
    out, written, frames, opacity = _write(tmp_path, fmt)
    expected = [p for f in formats_of(fmt) for p in out.frame_files(f)]
    assert written[:-1] == expected and written[-1] == out.metadata      # metadata last
    listed = json.loads(str(read_metadata(out.metadata)["files"]))
    assert listed == [str(p.relative_to(tmp_path)) for p in expected]
    assert out.files() == expected + [out.metadata] and out.is_complete()
    for i in (0, 1):
        back = out.read_frame(i)
        assert back.dtype == np.float32 and back.shape == (12, 16, 3)
        if fmt == "exr":            # float frames and their opacity, exactly
            np.testing.assert_array_equal(back, frames[i])
            np.testing.assert_array_equal(out.stored_opacity(i), opacity[i])
        else:                       # 8-bit PNG (also what `both` is read from): no opacity
            assert np.abs(back - frames[i]).max() <= 0.5 / 255 + 1e-7
            assert out.stored_opacity(i) is None
    assert out.frame_size() == (12, 16)
    # the places: PNG in the pass folder, EXR beside it, the right camera's suffixed first
    assert out.frame_files("png")[0] == tmp_path / "training/snow_clean/alley_1_0003/frame_0003.png"
    assert out.frame_files("exr", right=True)[1] == \
        tmp_path / "training/snow_clean_right_exr/alley_1_0003/frame_0004.exr"


def test_a_new_format_is_one_module_and_one_line(tmp_path, monkeypatch):
    """A format registered in FRAME_FORMATS (here a toy one storing float32 .npy files) is
    offered by the writer and `both`, placed by PairOutput and read back, nothing else touched."""
    def write(path: Path, rgb, opacity) -> Path:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, np.asarray(rgb, np.float32))
        return path

    npy = FrameFormat(name="npy", extension="npy", folder_suffix="_npy", write=write,
                      read=lambda p: np.load(p), size=lambda p: np.load(p).shape[:2])
    monkeypatch.setitem(formats.FRAME_FORMATS, "npy", npy)
    out, written, frames, _ = _write(tmp_path, "npy")
    assert written[0] == tmp_path / "training/snow_clean_npy/alley_1_0003/frame_0003.npy"
    np.testing.assert_array_equal(out.read_frame(1), frames[1])
    both, written, _, _ = _write(tmp_path / "both", "both")
    assert [p.suffix for p in written[:-1]] == [".png", ".png", ".exr", ".exr", ".npy", ".npy"]
    assert len(both.right_files()) == 3 * 2 + 4 + 2        # every format's right frames, geometry, provenance
