"""Combined presets above the engine: each layer's seed in a run, what `presets` and `inspect` show,
sequences of combined weather fields, and the one-line refusal of what cannot draw them yet."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from engine_scenes import plane_pair, wisps
from weathergen.engine import (EXAMPLE_COMBINATIONS, LayeredParticles, layer_seed, load_preset,
                               sample_layers, scene_seed)
from weathergen.framepair import PairId
from weathergen.jobs import layer_seeds, pair_particles, pair_seed, weather_seed
from run_helpers import cli_run as run, one_line_error




def test_each_layer_seed_comes_from_its_own_models_seed():
    c = load_preset("snow+fog-light")
    first, second = PairId("sintel", "training", "alley_1", 1), PairId("sintel", "training", "alley_1", 2)
    s1, s2 = layer_seeds(c, 7, first), layer_seeds(c, 7, second)
    # the paper layer: from the pair's own seed, another for every pair
    assert s1[0] == layer_seed(pair_seed(7, first), "snow") and s1[0] != s2[0]
    # the field layer: from the scene's field seed, one field for the whole scene
    assert s1[1] == s2[1] == layer_seed(scene_seed(7, "sintel", "training", "alley_1"), "fog-light")
    assert layer_seeds(c, 8, first) != s1
    assert weather_seed(c, 7, first) == pair_seed(7, first)


def test_a_runs_pair_samples_every_layer_with_its_seed():
    pair = plane_pair(40, 56)
    c = load_preset("snow+fog-light", {"snow.count": "100"})
    layers = pair_particles(pair, c, 3, frame_rate=30.0)
    assert isinstance(layers, LayeredParticles)
    expected = sample_layers(pair, c, layer_seeds(c, 3, pair.id), frame_rate=30.0)
    for a, b in zip(layers.layers, expected.layers):
        assert torch.equal(a.position, b.position) and a.settings == b.settings


@pytest.mark.parametrize("command", ["render", "attack"])
def test_bad_combinations_are_refused_in_one_line(tmp_path, command):
    out = tmp_path / "out"
    line = one_line_error(run(command, "--preset", "snow+", "--out", out))
    assert "--preset snow+: layer 2 of 2 is empty" in line and not out.exists()
    line = one_line_error(run(command, "--preset", "snow+nothing-like-it", "--out", out))
    assert "--preset snow+nothing-like-it: layer 2 (nothing-like-it)" in line
    assert not out.exists()
    line = one_line_error(run(command, "--preset", "snow+fog-light", "--set", "density=3", "--out", out))
    assert "--set density: not a key of layer 1 (snow, a paper preset)" in line
    line = one_line_error(run(command, "--preset", "snow-light+rain-light", "--set",
                              "snow-light.frame_rate=24", "--out", out))
    assert "field layers have different frame rates" in line and not out.exists()


def test_stereo_draws_a_combination_into_the_right_camera(tmp_path):
    """KITTI with image_3: `--stereo` with combined weather writes the right camera's frames, with
    weather that is not the left frame's; in the library, one layer seen from the right camera
    gives the frames of that record's own right-camera render, byte for byte."""
    from fake_datasets import demo_sequence, write_fake_kitti_stereo
    from weathergen.engine import View, load_templates, reference_transforms
    from weathergen.engine.rendering.renderer import pair_starts
    from weathergen.engine.rendering.stereo import render_right, render_right_layers, stereo_view
    from weathergen.io.images import read_image

    _, pairs = demo_sequence("street")
    split = write_fake_kitti_stereo(tmp_path / "kitti", pairs[0])
    out = tmp_path / "stereo"
    res = run("render", "--dataset", "kitti", "--root", tmp_path / "kitti", "--preset",
              "snow-moderate+fog-light", "--set", "far=5", "--stereo", "--out", out)
    assert res.exit_code == 0, res.output
    name = "snow-moderate+fog-light_clean"
    left, right = (read_image(out / "training" / folder / "000004_0010" / "frame_0010.png")
                   for folder in (name, name + "_right"))
    original = read_image(split / "image_3" / "000004_10.png")
    assert np.abs(right - original).max() > 0.1 and np.abs(right - left).max() > 0.1

    pair = pairs[0]
    record = pair_particles(pair, load_preset("snow-moderate", {"far": "5"}), 0, frame_rate=10.0)
    shift = torch.tensor([[1, 0, 0, -0.54], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
                         dtype=torch.float64)
    _, c1, c2 = reference_transforms(pair)
    views = [stereo_view(View(pair.intrinsics, cam, depth), shift, depth)
             for depth, cam in ((pair.depth1, c1), (pair.depth2, c2))]
    images = (pair.image1, pair.image2)
    frames, opacities = render_right_layers(images, views, LayeredParticles((record,), ("s",)))
    start1, start2, disp = pair_starts(record, torch.float32, torch.device("cpu"))
    lib = load_templates(record.settings.templates)
    for t, start in enumerate((start1, start2)):
        alone, alpha = render_right(images[t], views[t], record, start, disp, lib)
        assert torch.equal(frames[t], alone)
        # the layered opacity is 1 − Π (1 − clamp(A)): one layer's, up to float32's rounding
        assert torch.allclose(opacities[t], alpha, rtol=0, atol=1e-6)


def test_a_sequence_refuses_a_combination_with_a_paper_layer_in_one_line(tmp_path):
    out = tmp_path / "out"
    line = one_line_error(run("render", "--preset", "snow-light+snow", "--sequence", "--out",
                              out))
    assert "needs weather-field presets in every layer" in line
    assert "layer 'snow' of 'snow-light+snow' is a paper preset" in line
    assert not out.exists()


SEQUENCE = ("--scenes", "street", "--frames-per-scene", "2", "--preset", "snow-light+fog-light",
            "--set", "far=5")


def test_a_combined_field_sequence_holds_the_pair_frames_and_rerenders_bit_identically(tmp_path):
    """Every layer a weather field: `--sequence` writes each frame once, the bytes of the same
    frame in the pair outputs (frame 2 of pair 1 is frame 1 of pair 2 there), with one
    metadata file per pair holding both layers; re-rendering from those particles gives the
    same bytes, and the preview plays it as a video."""
    import cv2

    from weathergen.engine import load_particles

    seq, pairs, again = tmp_path / "seq", tmp_path / "pairs", tmp_path / "again"
    for out, extra in ((seq, ("--sequence",)), (pairs, ())):
        res = run("render", "--out", out, *extra, *SEQUENCE)
        assert res.exit_code == 0, res.output
    name = "snow-light+fog-light_clean"
    frames = seq / "training" / name / "street"
    assert sorted(p.name for p in frames.iterdir()) == [f"frame_{n:04d}.png" for n in (1, 2, 3)]
    for n, pair_dir in ((1, "street_0001"), (2, "street_0001"), (2, "street_0002"),
                        (3, "street_0002")):
        same = (pairs / "training" / name / pair_dir / f"frame_{n:04d}.png").read_bytes()
        assert (frames / f"frame_{n:04d}.png").read_bytes() == same, (n, pair_dir)
    stored = load_particles(seq / "training" / "particles" / "street" / "frame_0001.npz")
    assert isinstance(stored, LayeredParticles) and stored.names == ("snow-light", "fog-light")
    res = run("render", "--particles", seq, "--sequence", "--scenes", "street",
              "--frames-per-scene", "2", "--out", again)
    assert res.exit_code == 0, res.output
    for n in (1, 2, 3):
        assert (again / "training" / name / "street" / f"frame_{n:04d}.png").read_bytes() == \
            (frames / f"frame_{n:04d}.png").read_bytes()
    video = tmp_path / "seq.mp4"
    assert run("preview", seq, "--video", video).exit_code == 0
    capture = cv2.VideoCapture(str(video))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 3 * 16    # its 3 frames, played to last 2 s
    capture.release()


ONE_PAIR = ("--scenes", "courtyard", "--frames-per-scene", "1")
#: the fog layer drawn as wisps of haze (particles, alpha blended) rather than as an atmosphere:
#: these tests are about layers of particles
WISPS = wisps("fog-light")
WISP_SETS = tuple(a for k, v in WISPS.items() for a in ("--set", f"{k}={v}"))


@pytest.fixture(scope="module")
def combined_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("combined") / "snow+fog-light"
    res = run("render", "--preset", "snow+fog-light", *WISP_SETS, *ONE_PAIR, "--particle-truth",
              "--out", out)
    assert res.exit_code == 0, res.output
    return out


PAIR = "courtyard_0001"


def test_render_draws_every_layer_into_one_pair(combined_out, demo_root):
    """The demo scene with snow and light fog: one metadata file holding both layers with a
    layer index per particle and each layer's seed, the particles those seeds sample, frames
    that differ from the clean ones, particle ground truth over both layers."""
    from weathergen.datasets import open_dataset
    from weathergen.engine import load_particles, particle_truth, render_pair
    from weathergen.io.images import read_image
    from weathergen.outputs import read_metadata

    split = combined_out / "training"
    npz = split / "particles" / PAIR / "frame_0001.npz"
    arrays = read_metadata(npz)
    stored = load_particles(npz)
    assert isinstance(stored, LayeredParticles) and stored.names == ("snow", "fog-light")
    assert stored.counts[0] == 454 and stored.counts[1] > 0
    assert np.array_equal(arrays["layer"], np.repeat([0, 1], stored.counts))
    demo = open_dataset("demo", scenes=["courtyard"], frames_per_scene=1)
    pair = demo.load(demo.pairs()[0])
    preset = load_preset("snow+fog-light", WISPS)
    seeds = layer_seeds(preset, 0, pair.id)
    assert arrays["layer_seeds"].tolist() == list(seeds)
    sampled = pair_particles(pair, preset, 0, frame_rate=demo.frame_rate)
    for a, b in zip(stored.layers, sampled.layers):
        assert torch.equal(a.position, b.position) and a.settings == b.settings
    manifest = json.loads((combined_out / "manifest.json").read_text())
    assert manifest["preset"]["model"] == "combined"
    clean = pair.image1.permute(1, 2, 0).numpy()
    frame = read_image(split / "snow+fog-light_clean" / PAIR / "frame_0001.png")
    assert np.abs(frame - clean).mean() > 0.03           # snow alone: about 0.025
    # the written frame is the engine's layered render of the stored layers
    out = render_pair(pair, stored)
    assert np.abs(out.image1[0].permute(1, 2, 0).numpy() - frame).max() <= 0.5 / 255 + 1e-6
    truth = particle_truth(pair, stored)
    # each layer rendered alone as the combination draws it (large billboards on coarse grids
    # against each block's mean depth: docs/engine.md)
    alone = [particle_truth(pair, LayeredParticles((layer,), (name,)))
             for layer, name in zip(stored.layers, stored.names)]
    snow, fog = (a.weight for a in alone)
    # the layers' weights add up, but for the snow behind the (alpha) fog, which it dims
    assert bool((truth.weight <= snow + fog + 1e-5).all())
    assert bool((truth.weight >= fog - 1e-5).all())
    assert torch.allclose(truth.weight[snow == 0], fog[snow == 0], atol=1e-6)
    assert torch.allclose(truth.weight[fog == 0], snow[fog == 0], atol=1e-6)
    opacity = read_image(split / "particle_opacity" / PAIR / "frame_0001.png")
    assert abs(float(np.mean(opacity)) - float(truth.opacity.mean())) < 0.01


def test_rerendering_a_combination_gives_the_same_bytes(combined_out, tmp_path):
    import hashlib

    again = tmp_path / "again"
    res = run("render", "--particles", combined_out, *ONE_PAIR, "--out", again)
    assert res.exit_code == 0, res.output
    for name in ("frame_0001.png", "frame_0002.png"):
        a, b = (root / "training" / "snow+fog-light_clean" / PAIR / name
                for root in (combined_out, again))
        assert hashlib.sha256(a.read_bytes()).digest() == hashlib.sha256(b.read_bytes()).digest()
    line = one_line_error(run("render", "--particles", combined_out, *ONE_PAIR, "--set",
                              "blend=alpha", "--out", tmp_path / "x"))
    assert "--set blend: the stored particles are of the combined preset" in line


def test_a_severity_ladder_keeps_its_counts_when_rendered_in_combination(tmp_path):
    """snow-light+rain-moderate: each layer holds the particles its preset alone samples with
    the layer's seed, so the ladders' ratios (light vs moderate) hold in combination."""
    from weathergen.datasets import open_dataset
    from weathergen.engine import load_particles, sample_weather

    out = tmp_path / "ladder"
    res = run("render", "--preset", "snow-light+rain-moderate", *ONE_PAIR, "--out", out)
    assert res.exit_code == 0, res.output
    stored = load_particles(out / "training" / "particles" / PAIR / "frame_0001.npz")
    demo = open_dataset("demo", scenes=["courtyard"], frames_per_scene=1)
    pair = demo.load(demo.pairs()[0])
    preset = load_preset("snow-light+rain-moderate")
    for layer, seed, record in zip(preset.layers, layer_seeds(preset, 0, pair.id), stored.layers):
        alone = sample_weather(pair, load_preset(layer.name), seed, frame_rate=demo.frame_rate)
        assert record.count == alone.count > 0, layer.name


def test_weather_augment_renders_a_combination():
    """Per sample and per batch, the same frames; every layer is in them."""
    from weathergen.datasets import open_dataset
    from weathergen.training import PairDataset, WeatherAugment, collate_pairs

    data = PairDataset(open_dataset("demo", scenes=["courtyard"], frames_per_scene=2))
    samples = [data[i] for i in range(len(data))]
    aug = WeatherAugment("snow+fog", p=1.0, seed=3, overrides={"snow.count": 150},
                         keep_particles=True)
    one = [aug(s) for s in samples]
    assert all(isinstance(s.particles, LayeredParticles) for s in one)
    assert one[0].particles.names == ("snow", "fog")
    batched = aug.apply_batch(collate_pairs(samples))
    for k, s in enumerate(one):
        assert torch.equal(batched.pairs.image1[k], s.pair.image1)
        assert torch.equal(batched.pairs.image2[k], s.pair.image2)
        assert not torch.equal(s.pair.image1, samples[k].pair.image1)
    assert aug.sources[0].model == "combined"
    mixed = WeatherAugment(["snow", "snow+fog"], p=1.0, seed=4, overrides={"count": 100})
    batch = mixed.apply_batch(collate_pairs(samples))
    assert all(w.rendered for w in batch.weather)


def test_presets_lists_example_combinations_and_shows_each_layer():
    res = run("presets")
    assert res.exit_code == 0, res.output
    for name in EXAMPLE_COMBINATIONS:
        assert f" {name} " in res.output, name
    assert "rain-heavy (field) + fog-light (field)" in res.output
    res = run("presets", "snow+fog-light", "--set", "snow.count=77", "--set", "2.density=0.07")
    assert res.exit_code == 0, res.output
    assert "layer 1 of snow+fog-light: preset snow (paper model)" in res.output
    assert "layer 2 of snow+fog-light: preset fog-light (field model)" in res.output
    assert " 77 " in res.output and " 0.07 " in res.output
    line = one_line_error(run("presets", "snow+snow"))
    assert "layer 'snow' is given twice" in line


def test_inspect_shows_the_layers_of_a_metadata_file(tmp_path):
    from weathergen.outputs.metadata import pair_metadata, write_metadata

    pair = plane_pair(40, 56)
    c = load_preset("snow+fog", {"snow.count": "50", "fog.count": "3"})
    layers = sample_layers(pair, c, (1, 2), frame_rate=30.0)
    arrays = pair_metadata(layers, pair.id, 5, c.to_dict(), c.name, layer_seeds=(1, 2))
    arrays["files"] = np.array(json.dumps([]))
    path = write_metadata(tmp_path / "frame_0001.npz", arrays)
    res = run("inspect", path)
    assert res.exit_code == 0, res.output
    assert "snow+fog" in res.output and "(v4)" in res.output
    assert "snow: 50 particles" in res.output and "fog: 3 particles" in res.output
    assert "per-particle values of layer snow" in res.output
    assert "per-particle values of layer fog" in res.output


def test_preview_and_the_weather_region_read_a_combined_output(combined_out, tmp_path):
    """`preview` re-renders the opacity from every stored layer, and `evaluate`'s weather
    region covers the pixels of both layers."""
    from weathergen.attack.evaluate import weather_region
    from weathergen.datasets import open_dataset
    from weathergen.outputs import WeatherFolder

    res = run("preview", combined_out, "--out", tmp_path / "sheet.png")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "sheet.png").stat().st_size > 1000
    folder = WeatherFolder.open(combined_out)
    pair_id = folder.pairs[0]
    stored = folder.particles(pair_id)
    assert isinstance(stored, LayeredParticles) and len(stored.layers) == 2
    demo = open_dataset("demo", scenes=["courtyard"], frames_per_scene=1)
    pair = demo.load(demo.pairs()[0])
    covered = weather_region(folder, pair_id, pair)
    alone = [weather_region_of(pair, LayeredParticles((layer,), (name,)))
             for layer, name in zip(stored.layers, stored.names)]
    union = alone[0] | alone[1]
    # every pixel of either layer, but for the few where dimmed snow over thin fog falls under
    # the mask's threshold
    assert int((union & ~covered).sum()) <= 1e-3 * int(union.sum()) and int(covered.sum()) > 0
    assert bool((covered >= (alone[0] & ~alone[1])).all())


def weather_region_of(pair, record):
    from weathergen.engine import render_pair
    from weathergen.flow import weather_mask

    with torch.no_grad():
        out = render_pair(pair, record)
    return weather_mask(out.opacity1, out.opacity2)[0, 0]
