"""`weathergen render` with the atmosphere: the fog ladder and combined weather end to end on the
demo scene (pairs, --sequence, EXR opacity, particle truth, --stereo, re-rendering), and the
scene's one airlight."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner

from weathergen.cli.main import _register, cli
from weathergen.io.images import read_image
from run_helpers import output_digests

FOG = ("--scenes", "street", "--frames-per-scene", "2", "--preset", "fog-heavy")


def run(*args):
    _register()
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def fog_run(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("fog") / "pairs"
    res = run("render", "--out", out, "--format", "both", *FOG)
    assert res.exit_code == 0, res.output
    return out


def test_render_fog_heavy_on_the_demo_scene(fog_run, demo_root):
    from weathergen.io.exr import read_exr
    from weathergen.io.sintel_formats import read_dpt

    root = fog_run / "training"
    manifest = json.loads((fog_run / "manifest.json").read_text())
    assert manifest["preset"]["visibility"] == 100.0 and manifest["preset"]["density"] == 0
    pair = root / "fog-heavy_clean" / "street_0001"
    fogged = read_image(pair / "frame_0001.png")
    clean = read_image(demo_root / "training" / "clean" / "street" / "frame_0001.png")
    exr = read_exr(root / "fog-heavy_clean_exr" / "street_0001" / "frame_0001.exr")
    opacity = exr["opacity"]
    # the frame is Koschmieder's composite of the clean frame and the stored airlight
    scalars = json.loads(str(np.load(root / "particles" / "street_0001" / "frame_0001.npz")
                             ["scalars"]))
    airlight = np.array(json.loads(scalars["atmosphere"][0])["airlight"], dtype=np.float32)
    t = 1 - opacity[..., None]
    assert np.abs(fogged - (clean * t + airlight * (1 - t))).max() <= 1.5 / 255
    assert np.abs(fogged - clean).mean() > 0.02
    depth = read_dpt(root / "depth" / "street_0001" / "frame_0001.dpt")
    # Koschmieder: 1 − t = 1 − exp(−β L), L ≥ depth, banks within 1 ± 0.5 of the mean density
    beta = -math.log(0.05) / 100.0
    assert np.all(opacity >= 1 - np.exp(-0.5 * beta * depth) - 1e-4)
    near, far = depth < np.quantile(depth, 0.2), depth > np.quantile(depth, 0.8)
    assert opacity[far].mean() > opacity[near].mean() + 0.1
    # the airlight is the scene's one estimate, shared by both frames and both pairs
    records = [np.load(root / "particles" / f"street_{n:04d}" / f"frame_{n:04d}.npz")
               for n in (1, 2)]
    airlights = {tuple(json.loads(json.loads(str(r["scalars"]))["atmosphere"][0])["airlight"])
                 for r in records}
    assert len(airlights) == 1
    # frame 2 of pair 1 is frame 1 of pair 2, byte for byte
    a = (root / "fog-heavy_clean" / "street_0001" / "frame_0002.png").read_bytes()
    b = (root / "fog-heavy_clean" / "street_0002" / "frame_0002.png").read_bytes()
    assert a == b


def test_rerendering_fog_from_its_particles_is_bit_identical(fog_run, tmp_path):
    out = tmp_path / "again"
    res = run("render", "--particles", fog_run, "--scenes", "street", "--frames-per-scene", "2",
              "--format", "both", "--out", out)
    assert res.exit_code == 0, res.output
    assert output_digests(out / "training" / "fog-heavy_clean") == \
        output_digests(fog_run / "training" / "fog-heavy_clean")


def test_combined_rain_and_fog_sequence_end_to_end(tmp_path, demo_root):
    args = ("--scenes", "street", "--frames-per-scene", "2", "--preset", "rain-heavy+fog-light",
            "--set", "rain-heavy.far=5", "--set", "rain-heavy.density=60")
    pairs, seq = tmp_path / "pairs", tmp_path / "seq"
    assert run("render", "--out", pairs, "--particle-truth", *args).exit_code == 0
    res = run("render", "--out", seq, "--sequence", *args)
    assert res.exit_code == 0, res.output
    name = "rain-heavy+fog-light_clean"
    for n in (1, 2, 3):
        pair_dir = f"street_{min(n, 2):04d}"
        assert (seq / "training" / name / "street" / f"frame_{n:04d}.png").read_bytes() == \
            (pairs / "training" / name / pair_dir / f"frame_{n:04d}.png").read_bytes()
    opacity = read_image(pairs / "training" / "particle_opacity" / "street_0001"
                         / "frame_0001.png")[..., 0]
    assert 0 < (opacity > 0).mean() < 1


def test_stereo_right_camera_sees_the_same_fog(tmp_path, demo_root):
    import shutil

    from fake_datasets import demo_sequence, write_fake_kitti

    _, pairs = demo_sequence("street")
    split = write_fake_kitti(tmp_path / "kitti", pairs[0], scene="000004")
    (split / "image_3").mkdir()
    for n in (10, 11):
        shutil.copy(split / "image_2" / f"000004_{n}.png", split / "image_3" / f"000004_{n}.png")
    out = tmp_path / "stereo"
    res = run("render", "--dataset", "kitti", "--root", tmp_path / "kitti", "--preset",
              "fog-heavy", "--stereo", "--format", "both", "--out", out)
    assert res.exit_code == 0, res.output
    from weathergen.io.exr import read_exr

    left = read_exr(out / "training" / "fog-heavy_clean_exr" / "000004_0010" / "frame_0010.exr")
    right = read_exr(out / "training" / "fog-heavy_clean_right_exr" / "000004_0010"
                     / "frame_0010.exr")
    # the same scene seen from 0.54 m aside: nearly the same fog (the right view's pixels that
    # no left pixel sees have no depth: they take the far depth, and the sky's opacity)
    assert abs(float(np.median(left["opacity"])) - float(np.median(right["opacity"]))) < 0.05
    assert float(right["opacity"].min()) > 0


def test_preview_of_a_fog_output_shows_the_air(fog_run, tmp_path):
    """`preview` reads an output whose records hold only an atmosphere (no particles) and
    re-renders it: the stored records' opacity is the air's, > 0 on every pixel."""
    import torch

    from weathergen.datasets import open_dataset
    from weathergen.engine import render_pair
    from weathergen.outputs import WeatherFolder

    res = run("preview", fog_run, "--out", tmp_path / "sheet.png")
    assert res.exit_code == 0, res.output
    assert read_image(tmp_path / "sheet.png").shape[0] > 50
    folder = WeatherFolder.open(fog_run)
    stored = folder.particles(folder.pairs[0])
    assert stored.count == 0 and stored.atmosphere is not None
    demo = open_dataset("demo", scenes=["street"], frames_per_scene=1)
    with torch.no_grad():
        out = render_pair(demo.load(demo.pairs()[0]), stored)
    assert float(out.opacity1.min()) > 0


def test_weather_augment_draws_the_atmosphere_per_sample_and_per_batch():
    """WeatherAugment with fog-heavy: the far half of the frame moves towards the airlight more
    than the near half; a batch gives each sample's frames byte for byte."""
    import torch

    from weathergen.datasets import open_dataset
    from weathergen.training import PairDataset, WeatherAugment, collate_pairs

    data = PairDataset(open_dataset("demo", scenes=["street"], frames_per_scene=2))
    samples = [data[i] for i in range(len(data))]
    aug = WeatherAugment("fog-heavy", p=1.0, seed=5, keep_particles=True)
    one = [aug(s) for s in samples]
    for s, clean in zip(one, samples):
        atmosphere = s.particles.atmosphere
        assert atmosphere is not None and atmosphere.extinction > 0
        change = (s.pair.image1 - clean.pair.image1).abs().mean(0)
        depth = clean.pair.depth1[0]
        near, far = depth < depth.quantile(0.2), depth > depth.quantile(0.8)
        assert float(change[far].mean()) > float(change[near].mean()) + 0.02
    batched = aug.apply_batch(collate_pairs(samples))
    for k, s in enumerate(one):
        assert torch.equal(batched.pairs.image1[k], s.pair.image1)
        assert torch.equal(batched.pairs.image2[k], s.pair.image2)
