"""The Sintel reader on tiny fake trees: selection, scaling, cameras and every bad-input path."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from weathergen.datasets import DATASETS, load_scene_scales, open_dataset
from weathergen.errors import ConfigError, DatasetError, FormatError
from weathergen.io.sintel_formats import read_cam, write_dpt


def ids(ds):
    return [(r.id.scene, r.id.frame) for r in ds.pairs()]


def test_lists_pairs_of_every_scene(fake_sintel):
    ds = open_dataset("sintel", fake_sintel)
    assert ids(ds) == [(s, f) for s in ("alley", "bamboo") for f in (1, 2, 3)]


def test_selection_options(fake_sintel):
    assert ids(open_dataset("sintel", fake_sintel, scenes=["bamboo"])) == [("bamboo", f) for f in (1, 2, 3)]
    assert ids(open_dataset("sintel", fake_sintel, from_scene="bamboo")) == [("bamboo", f) for f in (1, 2, 3)]
    assert ids(open_dataset("sintel", fake_sintel, frames_per_scene=2)) == [
        ("alley", 1), ("alley", 2), ("bamboo", 1), ("bamboo", 2)]
    assert ids(open_dataset("sintel", fake_sintel, first_frame=2, frames_per_scene=1)) == [
        ("alley", 2), ("bamboo", 2)]


def test_unknown_scene_lists_known_ones(fake_sintel):
    with pytest.raises(ConfigError, match="no scene named cave.*available: alley, bamboo"):
        open_dataset("sintel", fake_sintel, scenes=["cave"]).pairs()


def test_unknown_dataset_lists_known_ones():
    with pytest.raises(ConfigError, match="known: " + ", ".join(sorted(DATASETS))):
        open_dataset("middlebury", "/tmp")


def test_missing_root_and_layout(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        open_dataset("sintel", tmp_path / "none")
    with pytest.raises(DatasetError, match="expected Sintel layout"):
        open_dataset("sintel", tmp_path).pairs()


def test_load_record(fake_sintel):
    ds = open_dataset("sintel", fake_sintel)
    pair = ds.load(ds.pairs()[0])
    assert pair.image1.shape == (3, 12, 16) and pair.image1.dtype == torch.float32
    assert 0 <= pair.image1.min() and pair.image1.max() <= 1
    assert pair.depth1.shape == (1, 12, 16)
    assert pair.flow.shape == (2, 12, 16)
    assert pair.flow_valid.all()
    # cameras: E_i translation = (-0.1 i, 0, 0.05 i), so cam2_from_cam1 translates by (-0.1, 0, 0.05)
    torch.testing.assert_close(pair.cam2_from_cam1[:3, 3], torch.tensor([-0.1, 0.0, 0.05], dtype=torch.float64))
    torch.testing.assert_close(pair.cam2_from_world @ torch.linalg.inv(pair.cam1_from_world), pair.cam2_from_cam1)
    assert str(pair.id) == "sintel/training/alley/0001"


def test_depth_scale_scales_depth_and_translation(fake_sintel, tmp_path):
    table = tmp_path / "scales.toml"
    table.write_text("alley = 0.5\n")
    ds = open_dataset("sintel", fake_sintel, depth_scale=2.0, scene_scales=load_scene_scales(table))
    a, b = (ds.load(r) for r in ds.pairs()[::3])
    assert a.id.scene == "alley" and b.id.scene == "bamboo"
    torch.testing.assert_close(a.depth1, torch.full((1, 12, 16), 2.1))          # 2.1 * 2 * 0.5
    torch.testing.assert_close(b.depth1, torch.full((1, 12, 16), 3.1 * 2.0))
    torch.testing.assert_close(b.cam2_from_cam1[:3, 3], torch.tensor([-0.2, 0.0, 0.1], dtype=torch.float64))
    assert a.depth_scale == 1.0 and b.depth_scale == 2.0


def test_bad_scene_scale_table(tmp_path):
    table = tmp_path / "scales.toml"
    table.write_text("alley = -1\n")
    with pytest.raises(ConfigError, match="alley.*positive"):
        load_scene_scales(table)


def test_drop_camera_translation(fake_sintel):
    ds = open_dataset("sintel", fake_sintel, camera_translation=False)
    pair = ds.load(ds.pairs()[0])
    assert torch.equal(pair.cam2_from_cam1[:3, 3], torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(pair.cam2_from_world @ torch.linalg.inv(pair.cam1_from_world), pair.cam2_from_cam1)


def test_test_split_has_no_depth(fake_sintel):
    ds = open_dataset("sintel", fake_sintel, split="test")
    ref = ds.pairs()[0]
    with pytest.raises(DatasetError, match="depth file is missing.*test split ships no depth"):
        ds.load(ref)


def test_size_mismatch_names_the_depth_file(fake_sintel):
    bad = fake_sintel / "training/depth/alley/frame_0002.dpt"
    write_dpt(bad, np.ones((5, 5), np.float32))
    ds = open_dataset("sintel", fake_sintel)
    with pytest.raises(DatasetError, match=r"frame_0002.dpt: depth is 5x5 but the image is 16x12"):
        ds.load(ds.pairs()[0])


@pytest.mark.parametrize("value,match", [(np.nan, "non-finite"), (0.0, "zero or negative"), (-1.0, "zero or negative")])
def test_bad_depth_values(fake_sintel, value, match):
    d = np.ones((12, 16), np.float32)
    d[3, 4] = value
    write_dpt(fake_sintel / "training/depth/alley/frame_0001.dpt", d)
    ds = open_dataset("sintel", fake_sintel)
    with pytest.raises(DatasetError, match=match):
        ds.load(ds.pairs()[0])


def test_corrupt_image_and_header(fake_sintel):
    (fake_sintel / "training/clean/alley/frame_0001.png").write_bytes(b"not a png")
    (fake_sintel / "training/camdata_left/bamboo/frame_0002.cam").write_bytes(b"\0" * 10)
    ds = open_dataset("sintel", fake_sintel)
    refs = ds.pairs()
    with pytest.raises(FormatError, match="frame_0001.png: cannot be decoded"):
        ds.load(refs[0])
    with pytest.raises(FormatError, match="frame_0002.cam"):
        ds.load(refs[3])
    assert "cannot be decoded" in ds.check(refs[0])
    assert ds.check(refs[1]) is None


def test_invalid_mask(fake_sintel):
    from weathergen.io.images import write_png

    mask = np.zeros((12, 16), np.uint8)
    mask[0, :4] = 255
    write_png(fake_sintel / "training/invalid/alley/frame_0001.png", mask)
    ds = open_dataset("sintel", fake_sintel)
    pair = ds.load(ds.pairs()[0])
    assert pair.flow_valid.sum() == 12 * 16 - 4
    assert not pair.flow_valid[0, 0, :4].any()


def test_demo_dataset_reads_without_root(demo_root):
    ds = open_dataset("demo")
    assert ds.root == demo_root
    assert len(ds.pairs()) >= 4
    k, _ = read_cam(ds.pairs()[0].files["cam1"])
    assert k[0, 0] > 0


def test_records_follow_the_documented_conventions(fake_sintel, demo_root):
    """framepair.py's dtypes, ranges and matrix forms hold for what the readers return."""
    for ds in (open_dataset("sintel", fake_sintel), open_dataset("demo")):
        pair = ds.load(ds.pairs()[0])
        for name in ("image1", "image2", "depth1", "depth2", "flow"):
            assert getattr(pair, name).dtype == torch.float32, name
        for name in ("intrinsics", "cam2_from_cam1", "cam1_from_world", "cam2_from_world"):
            assert getattr(pair, name).dtype == torch.float64, name
        assert pair.flow_valid.dtype == torch.bool
        assert 0 <= float(pair.image1.min()) and float(pair.image1.max()) <= 1
        assert pair.intrinsics[2].tolist() == [0, 0, 1]
        assert pair.cam2_from_cam1[3].tolist() == [0, 0, 0, 1]
        torch.testing.assert_close(pair.cam2_from_cam1,
                                   pair.cam2_from_world @ torch.linalg.inv(pair.cam1_from_world))


@pytest.mark.parametrize("field,value,message", [
    ("image1", lambda p: (p.image1 * 255).to(torch.uint8), "image1 is torch.uint8"),
    ("image2", lambda p: p.image2 + 1.5, "image2 has values outside"),
    ("intrinsics", lambda p: p.intrinsics[:2], "intrinsics is torch.float64 of shape (2, 3)"),
    ("flow_valid", lambda p: p.flow_valid.float(), "flow_valid is torch.float32"),
])
def test_validate_rejects_records_that_break_the_conventions(fake_sintel, field, value, message):
    from dataclasses import replace

    ds = open_dataset("sintel", fake_sintel)
    pair = ds.load(ds.pairs()[0])
    with pytest.raises(DatasetError, match=re.escape(message)):
        replace(pair, **{field: value(pair)}).validate()


def test_size_mismatch_names_the_odd_frame(fake_sintel):
    from weathergen.io.images import write_png

    write_png(fake_sintel / "training/clean/alley/frame_0002.png", np.zeros((10, 10, 3)))
    ds = open_dataset("sintel", fake_sintel, scenes=["alley"])
    refs = ds.pairs()
    # frame 2 is the second frame of pair 1 and the first frame of pair 2: both name it
    for ref in refs[:2]:
        with pytest.raises(DatasetError, match=r"clean/alley/frame_0002.png: frame is 10x10 but the "
                                               r"other frame and the depth maps are 16x12"):
            ds.load(ref)
