"""The README's pictures: regenerating them leaves the tracked files alone unless they really changed."""

from __future__ import annotations

import hashlib
import importlib.util
import shutil

import numpy as np

from conftest import PROJECT_ROOT


def _script():
    spec = importlib.util.spec_from_file_location("readme_images", PROJECT_ROOT / "scripts" / "readme_images.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_regenerating_the_readme_picture_changes_no_byte(tmp_path):
    from weathergen.io.images import read_raw, write_png

    script = _script()
    tracked = PROJECT_ROOT / "docs" / "images" / "presets.png"
    copy = tmp_path / "presets.png"
    shutil.copy(tracked, copy)
    assert script.main(copy) is False
    assert hashlib.sha256(copy.read_bytes()).digest() == hashlib.sha256(tracked.read_bytes()).digest()
    # the tracked picture is what the code draws today (up to rounding of a few pixels)
    fresh = script.render_sheet()
    diff = np.abs(fresh.astype(int) - read_raw(tracked)[..., ::-1].astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3
    # a picture that is really out of date is rewritten
    write_png(copy, np.zeros_like(fresh))
    assert script.main(copy) is True
    np.testing.assert_array_equal(read_raw(copy)[..., ::-1], fresh)


def test_the_video_still_is_a_frame_of_the_video_the_code_makes_today(tmp_path):
    from weathergen.io.images import read_raw

    script = _script()
    tracked = PROJECT_ROOT / "docs" / "images" / "video-still.png"
    fresh = script.render_video_still()
    assert fresh.shape == (176, 3 * 384, 3)            # input | weather | opacity
    diff = np.abs(fresh.astype(int) - read_raw(tracked)[..., ::-1].astype(int))
    assert diff.max() <= 1 and (diff > 0).mean() < 1e-3
    copy = tmp_path / "still.png"
    shutil.copy(tracked, copy)
    assert script.main_video_still(copy) is False
    assert copy.read_bytes() == tracked.read_bytes()
