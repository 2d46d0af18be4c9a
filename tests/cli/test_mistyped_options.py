"""Options a person mistypes: a video preview's width, frame rate and cycles out of their
documented range, and a benchmark grid left empty, are refused before any work, on the command
line (exit 2) and in the library (ConfigError naming the parameter)."""

from __future__ import annotations

import pytest

from weathergen.benchmark import BenchmarkSpec
from weathergen.errors import ConfigError
from weathergen.render import contact_sheet, video_preview
from weathergen.render.preview import MAX_TILE_WIDTH
from weathergen.render.video import MAX_CYCLES, MAX_FPS, MIN_FPS
from run_helpers import cli_run as run, one_line_error




@pytest.mark.parametrize("option, value, shown", [
    ("--width", "100000", f"64<=x<={MAX_TILE_WIDTH}"),
    ("--fps", "1e9", f"{MIN_FPS}<=x<={MAX_FPS}"),
    ("--fps", "inf", f"{MIN_FPS}<=x<={MAX_FPS}"),
    ("--cycles", "100000", f"1<=x<={MAX_CYCLES}"),
])
def test_preview_refuses_out_of_range_video_options_before_any_work(tmp_path, option, value,
                                                                    shown):
    video = tmp_path / "v.mp4"
    res = run("preview", tmp_path, "--video", video, option, value)
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    assert f"Invalid value for '{option}'" in res.output and shown in res.output
    assert not video.exists()
    help_text = run("preview", "--help").output.replace("\n", " ")
    assert f"[{shown}]" in " ".join(help_text.split())         # the range is documented


def test_preview_refuses_a_frame_rate_that_is_not_a_number(tmp_path):
    # click's range lets NaN through (every comparison is false): the library refuses it
    line = one_line_error(run("preview", tmp_path, "--video", tmp_path / "v.mp4", "--fps", "nan"))
    assert line == f"Error: --fps nan: must be in [{MIN_FPS:g}, {MAX_FPS:g}] frames per second"


@pytest.mark.parametrize("options, message", [
    (dict(width=100_000), f"width 100000: must be in [16, {MAX_TILE_WIDTH}] pixels"),
    (dict(width=8), f"width 8: must be in [16, {MAX_TILE_WIDTH}] pixels"),
    (dict(fps=1e9), "fps 1000000000.0: must be in"),
    (dict(fps=float("inf")), "fps inf: must be in"),
    (dict(fps=0.0), "fps 0.0: must be in"),
    (dict(cycles=100_000), f"cycles 100000: must be in [1, {MAX_CYCLES}]"),
    (dict(cycles=0), "cycles 0: must be in"),
])
def test_the_library_refuses_the_same_video_options(tmp_path, options, message):
    """Before reading the folder (here not a render output at all): the option is named."""
    with pytest.raises(ConfigError) as caught:
        video_preview(tmp_path, **options)
    assert str(caught.value).startswith(message)


def test_the_contact_sheet_refuses_a_tile_too_wide(tmp_path):
    with pytest.raises(ConfigError, match=rf"width 100000: must be in \[16, {MAX_TILE_WIDTH}\]"):
        contact_sheet(tmp_path, width=100_000)
    line = one_line_error(run("preview", tmp_path, "--width", str(MAX_TILE_WIDTH)))
    assert "preview takes the folder of a render output" in line    # the width itself is fine


@pytest.mark.parametrize("ladder", ["", ",", " , "])
def test_benchmark_refuses_a_ladder_list_naming_nothing(tmp_path, ladder):
    out = tmp_path / "b"
    line = one_line_error(run("benchmark", "--ladder", ladder, "--out", out))
    assert line.startswith(f"Error: --ladder {ladder!r} names no ladder: expected ")
    assert "snow" in line and not out.exists()


def test_benchmark_refuses_an_empty_grid(tmp_path):
    out = tmp_path / "b"
    line = one_line_error(run("benchmark", "--presets", "", "--lp", "", "--out", out))
    assert line == "Error: the grid is empty: --presets, --lp and --ladder name nothing to run"
    assert not out.exists()
    spec = BenchmarkSpec(dataset=None, out=out, networks=["raft"], presets=[], lp_methods=[])
    with pytest.raises(ConfigError, match="the grid is empty"):
        spec.cells()
    # presets alone, or Lp attacks alone, are a grid
    assert [c.label for c in BenchmarkSpec(dataset=None, out=out, networks=["raft"], presets=[],
                                           lp_methods=["pcfa"]).cells()] == ["pcfa"]
