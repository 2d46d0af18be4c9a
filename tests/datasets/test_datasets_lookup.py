"""Readers by name: the default reader, unknown names, what a reader needs."""

from __future__ import annotations

import pytest

from weathergen.cli.options import option_of
from weathergen.datasets import DATASETS, default_dataset, open_dataset
from weathergen.errors import ConfigError


def test_the_default_reader_is_the_demo_without_a_root_and_sintel_with_one():
    assert default_dataset(None) == "demo" and default_dataset("") == "demo"
    assert default_dataset("/data/MPI-Sintel") == "sintel"
    assert {"demo", "sintel"} <= set(DATASETS)


def test_a_reader_without_its_root_names_the_parameter():
    with pytest.raises(ConfigError) as missing:
        open_dataset("kitti")
    assert str(missing.value) == "dataset 'kitti' needs root, the folder it is stored in"
    assert missing.value.render(option_of) == "dataset 'kitti' needs --root, the folder it is stored in"
    with pytest.raises(ConfigError, match="unknown dataset 'hd1k'; known: custom, demo"):
        open_dataset("hd1k")


def test_readers_declare_their_traits():
    """Frame rate, passes, depth, native flow: each reader says them of itself (the documented
    values: Sintel, Spring and the demo 24 fps, KITTI 10 Hz, custom data unrecorded, 30)."""
    rates = {name: cls.frame_rate for name, cls in DATASETS.items()}
    assert rates == {"custom": 30.0, "demo": 24.0, "kitti": 10.0, "sintel": 24.0, "spring": 24.0}
    assert {n for n, cls in DATASETS.items() if not cls.single_pass} == {"demo", "sintel"}
    assert {n for n, cls in DATASETS.items() if cls.dense_depth} == {"demo", "sintel"}
    native = {n: (cls.native_flow.folder, cls.native_flow.format)
              for n, cls in DATASETS.items() if cls.native_flow is not None}
    assert native == {"kitti": ("flow_occ", "kitti-png"), "spring": ("flow_FW_left", "flo5")}
    assert {n for n, cls in DATASETS.items() if cls.stereo} == {"custom", "kitti", "spring"}


def test_a_reader_with_a_second_camera_reads_it_itself_under_any_name(tmp_path, demo_root):
    """Stereo is the reader class's trait: a KITTI reader registered under another name reads
    image_3 as KITTI does; a reader without a second camera is refused, naming those with one."""
    import shutil

    from fake_datasets import demo_sequence, write_fake_kitti
    from weathergen.datasets import KittiDataset, right_camera

    _, pairs = demo_sequence("street")
    split = write_fake_kitti(tmp_path / "kitti", pairs[0], scene="000004")
    (split / "image_3").mkdir()
    for n in (10, 11):
        shutil.copy(split / "image_2" / f"000004_{n}.png", split / "image_3" / f"000004_{n}.png")

    class Mirror(KittiDataset):
        name = "kitti-mirror"

    reader = Mirror(tmp_path / "kitti")
    pair = reader.load(reader.pairs()[0])
    assert pair.id.dataset == "kitti-mirror"
    right = right_camera(reader, pair)
    assert right.sources[0] == split / "image_3" / "000004_10.png"
    assert float(right.right_from_left[0, 3]) == pytest.approx(-pair.meta["baseline_m"] * pair.depth_scale)
    demo = open_dataset("demo", scenes=["street"], frames_per_scene=1)
    with pytest.raises(ConfigError, match="'demo' has no second camera; stereo rendering reads "
                                          "custom, kitti, spring"):
        right_camera(demo, demo.load(demo.pairs()[0]))


@pytest.mark.parametrize("name", sorted(DATASETS))
def test_the_options_a_reader_lists_are_keywords_it_takes(name):
    import inspect

    cls = DATASETS[name]
    taken = {p for klass in cls.__mro__ if "__init__" in vars(klass)
             for p, param in inspect.signature(klass.__init__).parameters.items()
             if param.kind is inspect.Parameter.KEYWORD_ONLY}
    assert set(cls.options) <= taken, set(cls.options) - taken
    # a sparse-depth reader takes the far depth; a dense one has none to take
    assert ("far_depth" in cls.options) == (not cls.dense_depth)


def test_a_reader_option_is_refused_for_readers_that_do_not_list_it(tmp_path):
    from click.testing import CliRunner

    from weathergen.cli.main import _register, cli

    _register()
    res = CliRunner().invoke(cli, ["check", "--fit-threshold", "2"])
    takers = ", ".join(n for n, cls in DATASETS.items() if "fit_threshold_px" in cls.options)
    assert res.exit_code == 2 and takers == "kitti"
    assert f"--fit-threshold applies to {takers} only, not to demo" in res.output


def test_help_texts_take_the_frame_rates_from_the_readers(monkeypatch):
    """The frame rates a help text lists come from the reader classes, not a copy of them."""
    from click.testing import CliRunner

    from weathergen.cli.main import cli
    from weathergen.datasets import frame_rates_text

    expected = {name: f"{cls.frame_rate:g}" for name, cls in DATASETS.items()}
    listed = {}
    for group in frame_rates_text().split("; "):
        names, rate = group.rsplit(" ", 1)
        listed.update({name: rate for name in names.split(", ")})
    assert listed == expected
    help_text = " ".join(CliRunner().invoke(cli, ["preview", "--help"]).output.split())
    assert f"the dataset's ({frame_rates_text()})" in help_text

    class Slow(DATASETS["demo"]):
        frame_rate = 12.5

    monkeypatch.setitem(DATASETS, "demo", Slow)
    assert "demo 12.5" in frame_rates_text()
