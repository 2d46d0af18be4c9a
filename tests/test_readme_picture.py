"""The pictures of the docs (scripts/make_images.py, `make images`): regenerating them leaves the
tracked files alone unless they really changed; the quick mode writes every picture it promises."""

from __future__ import annotations

import hashlib
import importlib.util
import shutil

import numpy as np
import pytest

from conftest import PROJECT_ROOT


def _script():
    spec = importlib.util.spec_from_file_location("make_images", PROJECT_ROOT / "scripts" / "make_images.py")
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


@pytest.mark.slow
def test_make_images_quick_writes_every_picture_it_promises(tmp_path, capsys):
    """`--quick` (a crop of the demo frame, a two-pair video) writes the four pictures, each the
    size its layout gives; the sheet holds one labelled tile per preset, paper and field, the
    atmosphere's ladder one per rung after the clean frame; a second run writes the same bytes;
    and the quick stand-ins are refused in docs/images."""
    import cv2
    import pytest

    from weathergen.engine.weather.presets import list_presets

    script = _script()
    out = tmp_path / "images"
    script.run(["--quick", "--out", str(out)])
    files = {p.name for p in out.iterdir()}
    assert files == {"presets.png", "video-still.png", "every-preset.png", "atmosphere.png", "depth.png"}
    _, _, h, w = script.QUICK_CROP
    assert read_png(out / "presets.png").shape == (2 * (h + script.LABEL_PX), 2 * w, 3)
    still = read_png(out / "video-still.png")
    assert still.shape[1] == 3 * 96 and still.shape[2] == 3
    names = script.sheet_order()
    assert sorted(names) == sorted(list_presets()) and len(names) == len(set(names)) >= 40
    sheet = read_png(out / "every-preset.png")
    rows = -(-len(names) // 6)
    assert sheet.shape == (rows * (h + script.LABEL_PX), 6 * w, 3)
    # each tile carries weather: it differs from the clean crop (a tile of a failed preset would not)
    pair, _ = script.demo_pair(quick=True)
    clean = pair.image1.permute(1, 2, 0).numpy() * 255
    for i, name in enumerate(names):
        r, c = divmod(i, 6)
        top = r * (h + script.LABEL_PX) + script.LABEL_PX
        tile = sheet[top:top + h, c * w:(c + 1) * w].astype(float)
        assert np.abs(tile - clean).mean() > 0.5, name
    ladder = read_png(out / "atmosphere.png")
    assert ladder.shape == (4 * (h + script.LABEL_PX), 4 * w, 3)
    first_tile = None
    for i, name in enumerate(script.LADDER):        # the clean tile first, then fogged ones
        r, c = divmod(2 * i, 4)                     # (each rung: its frame, then its opacity)
        top = r * (h + script.LABEL_PX) + script.LABEL_PX
        tile = ladder[top:top + h, c * w:(c + 1) * w].astype(float)
        if first_tile is None:                      # the clean frame, in the sheet's palette
            first_tile = tile
            assert np.abs(tile - clean).mean() < 4, name
        else:
            assert np.abs(tile - first_tile).mean() > 0.2, name   # mist on 25 m: ~0.35
        opacity = ladder[top:top + h, (c + 1) * w:(c + 2) * w].astype(float)
        assert name == "clean" or opacity.mean() > 2, name          # the air is there
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    script.run(["--quick", "--out", str(out)])
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first
    assert "(failed)" not in capsys.readouterr().out
    with pytest.raises(SystemExit, match="--quick"):
        script.run(["--quick"])
    assert cv2.imread(str(out / "every-preset.png")) is not None


def test_the_palette_png_keeps_the_picture_within_a_few_grey_levels(tmp_path):
    """The sheet's small PNG: a valid palette PNG (any reader opens it), the same bytes on every
    run, each pixel near its colour."""
    script = _script()
    rng = np.random.default_rng(0)
    ramp = np.linspace(0, 255, 200)
    rgb = np.stack(np.broadcast_arrays(ramp[None, :], ramp[:, None] * 0.5, 255 - ramp[None, :]), -1)
    rgb = np.clip(rgb + rng.normal(0, 4, rgb.shape), 0, 255).astype(np.uint8)
    data = script.palette_png(rgb)
    assert data == script.palette_png(rgb) and data[25] == 3          # colour type 3: palette
    path = tmp_path / "p.png"
    path.write_bytes(data)
    back = read_png(path)
    assert back.shape == rgb.shape
    assert np.abs(back.astype(int) - rgb.astype(int)).mean() < 4


def read_png(path):
    from weathergen.io.images import read_raw

    return read_raw(path)[..., ::-1]
