"""weathergen.training.augment: the weather transform, its keyed draws, and crops and flips after it."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from torch.utils.data import DataLoader

from weathergen.datasets import DATASETS, open_dataset
from weathergen.engine import load_preset, sample_field_particles
from weathergen.errors import ConfigError, ShapeError
from weathergen.framepair import _TENSOR_FIELDS
from weathergen.geometry import reprojection_flow
from weathergen.training import (Compose, PairDataset, PresetSource, RandomCrop, RandomFlip,
                                 WeatherAugment, collate_pairs, crop_pair, flip_pair, pair_of)

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

#: Few particles keep the tests fast (the presets' own count on the demo's 384x176 frames: 454).
LIGHT = {"count": 200}


@pytest.fixture(scope="module")
def demo(demo_root):
    return open_dataset("demo")


@pytest.fixture(scope="module")
def samples(demo):
    data = PairDataset(demo)
    return [data[i] for i in range(len(data))]


def test_p0_returns_the_input_bit_for_bit(samples):
    aug = WeatherAugment(["snow", "rain"], p=0.0, seed=1, overrides=LIGHT)
    for s in samples:
        out = aug(s)
        assert out.pair is s.pair and not out.weather.applied
    batch = collate_pairs(samples)
    out = aug.apply_batch(batch)
    for name in _TENSOR_FIELDS:
        a, b = getattr(out.pairs, name), getattr(batch.pairs, name)
        assert (a is None and b is None) or torch.equal(a, b), name


def test_paper_presets_follow_the_frame_size(samples):
    """As in `render`: the preset's count per 1024x436 frame scaled to the demo's 384x176 frames
    (3000 x 0.15138 -> 454), an explicit count exactly, in both places the transform runs."""
    sample = samples[0]
    assert sample.pair.size == (176, 384)
    scaled = WeatherAugment(["snow"], p=1.0, seed=3, keep_particles=True)
    assert scaled(sample).particles.count == 454
    assert scaled.prepare(sample).particles.count == 454
    exact = WeatherAugment(["snow"], p=1.0, seed=3, overrides={"count": 100}, keep_particles=True)
    assert exact(sample).particles.count == 100
    assert exact.prepare(sample).particles.count == 100


def test_p1_changes_every_pair_and_only_its_frames(samples):
    aug = WeatherAugment(["snow", "rain"], p=1.0, seed=1, overrides=LIGHT)
    drawn = set()
    for s in samples:
        out = aug(s)
        assert out.weather.applied and out.weather.rendered
        drawn.add(out.weather.source)
        for name in ("image1", "image2"):
            changed = getattr(out.pair, name) != getattr(s.pair, name)
            assert int(changed.any(0).sum()) > 100, name      # weather covers many pixels
        for name in _TENSOR_FIELDS:
            if name not in ("image1", "image2") and getattr(s.pair, name) is not None:
                assert torch.equal(getattr(out.pair, name), getattr(s.pair, name)), name
    assert drawn == {"snow", "rain"}


def test_draws_follow_the_probability_and_the_key():
    aug = WeatherAugment("snow", p=0.5, seed=7)
    draws = [aug.draw(i, 0) for i in range(400)]
    assert 160 < sum(d.applied for d in draws) < 240
    assert aug.draw(3, 2) == WeatherAugment("snow", p=0.5, seed=7).draw(3, 2)
    seeds = {d.seed for d in draws if d.applied}
    assert len(seeds) == sum(d.applied for d in draws)          # a new seed for every index
    assert sum(aug.draw(i, 0) != aug.draw(i, 1) for i in range(50)) > 20    # epochs differ


def loader_images(demo, workers, epoch, transform):
    data = PairDataset(demo, transform)
    data.set_epoch(epoch)
    loader = DataLoader(data, batch_size=2, num_workers=workers, collate_fn=collate_pairs)
    return [(b.indices.tolist(), b.pairs.image1.clone(), b.pairs.image2.clone(), b.weather)
            for b in loader]


def test_same_key_same_bytes_with_0_and_2_workers_new_epoch_new_weather(demo):
    aug = Compose([WeatherAugment(["snow", "rain"], p=1.0, seed=11, overrides=LIGHT),
                   RandomCrop((160, 360), seed=11), RandomFlip(0.5, 0.5, seed=11)])
    serial = loader_images(demo, 0, 1, aug)
    parallel = loader_images(demo, 2, 1, aug)
    for (i0, a1, a2, w0), (i1, b1, b2, w1) in zip(serial, parallel):
        assert i0 == i1 and w0 == w1
        assert torch.equal(a1, b1) and torch.equal(a2, b2)
        assert a1.numpy().tobytes() == b1.numpy().tobytes()
    other = loader_images(demo, 0, 2, aug)
    for (_, a1, _, w0), (_, c1, _, w2) in zip(serial, other):
        assert [w.seed for w in w0] != [w.seed for w in w2]
        for k in range(a1.shape[0]):
            assert not torch.equal(a1[k], c1[k])


@pytest.mark.parametrize("prepared", [False, True], ids=["sampled-per-batch", "prepared-in-workers"])
def test_batched_path_equals_per_sample_path(samples, prepared):
    aug = WeatherAugment(["snow", "rain"], p=0.5, seed=5, overrides=LIGHT)
    per_sample = collate_pairs([aug(s) for s in samples])
    inputs = [aug.prepare(s) for s in samples] if prepared else samples
    batched = aug.apply_batch(collate_pairs(inputs))
    assert batched.weather == per_sample.weather
    assert 0 < sum(w.applied for w in batched.weather) < len(samples)
    for name in ("image1", "image2"):
        assert torch.equal(getattr(batched.pairs, name), getattr(per_sample.pairs, name)), name
    for k, w in enumerate(batched.weather):
        if not w.applied:
            assert torch.equal(batched.pairs.image1[k], samples[k].pair.image1)
    assert batched.particles == [None] * len(samples)


def test_particles_prepared_in_two_workers_render_as_per_sample(demo, samples):
    aug = WeatherAugment("snow", p=0.5, seed=9, overrides=LIGHT)
    data = PairDataset(demo, aug.prepare)
    data.set_epoch(4)
    loader = DataLoader(data, batch_size=3, num_workers=2, collate_fn=collate_pairs)
    for batch in loader:
        rendered = aug.apply_batch(batch)
        expected = collate_pairs([aug(replace(samples[i], epoch=4)) for i in batch.indices.tolist()])
        assert rendered.weather == expected.weather
        assert torch.equal(rendered.pairs.image1, expected.pairs.image1)
        assert torch.equal(rendered.pairs.image2, expected.pairs.image2)


def with_dtype(sample, dtype):
    return replace(sample, pair=replace(sample.pair, image1=sample.pair.image1.to(dtype),
                                        image2=sample.pair.image2.to(dtype)))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batches_equal_per_sample_frames_in_either_precision(samples, dtype):
    """One render core for both paths: on the CPU the batched frames are bit for bit the
    per-sample ones in float32 and float64 (a pair's pixels do not depend on the batch)."""
    inputs = [with_dtype(s, dtype) for s in samples[:4]]
    aug = WeatherAugment(["snow", "rain"], p=0.7, seed=8, overrides=LIGHT)
    batched = aug.apply_batch(collate_pairs(inputs))
    assert {w.source for w in batched.weather if w.applied} == {"snow", "rain"}
    per_sample = collate_pairs([aug(s) for s in inputs])
    for name in ("image1", "image2"):
        x = getattr(batched.pairs, name)
        assert x.dtype == dtype
        assert torch.equal(x, getattr(per_sample.pairs, name)), name
        for k, w in enumerate(batched.weather):
            changed = int((x[k] != getattr(collate_pairs(inputs).pairs, name)[k]).any(0).sum())
            assert (changed > 100) == w.applied, (name, k)


def test_sampling_on_the_batch_device_is_the_cpus_on_a_cpu_batch(samples):
    aug = WeatherAugment(["snow", "rain"], p=1.0, seed=5, overrides=LIGHT, sample_on="device")
    ref = WeatherAugment(["snow", "rain"], p=1.0, seed=5, overrides=LIGHT)
    a, b = aug.apply_batch(collate_pairs(samples[:3])), ref.apply_batch(collate_pairs(samples[:3]))
    assert a.weather == b.weather
    assert torch.equal(a.pairs.image1, b.pairs.image1) and torch.equal(a.pairs.image2, b.pairs.image2)
    with pytest.raises(ConfigError, match="sample_on 'gpu'"):
        WeatherAugment("snow", sample_on="gpu")


@pytest.mark.cuda
def test_sampling_on_cuda_draws_the_cpus_weather(samples):
    """``sample_on="device"``: the same draws, the same particle counts, frames within one grey
    level of the CPU's but where a particle within rounding of a border is kept on one device
    only (a few in a thousand pixels)."""
    aug = WeatherAugment(["snow", "rain"], p=1.0, seed=6, overrides=LIGHT, sample_on="device",
                         keep_particles=True)
    cpu = aug.apply_batch(collate_pairs(samples[:3]))
    gpu = aug.apply_batch(collate_pairs(samples[:3]).to("cuda"))
    assert gpu.weather == cpu.weather
    for p, q in zip(gpu.particles, cpu.particles):
        assert p.position.device.type == "cuda" and p.count == q.count
        same = (p.position.cpu() == q.position).all(1)
        assert float(same.float().mean()) > 0.99
    for name in ("image1", "image2"):
        x, y = getattr(gpu.pairs, name).cpu(), getattr(cpu.pairs, name)
        grey = (x * 255).round() != (y * 255).round()
        assert float(grey.float().mean()) < 5e-3, name


@pytest.mark.cuda
def test_batched_path_on_cuda_matches_the_cpu(samples):
    """What docs/training.md promises for CUDA: the same draws and particles, and frames within
    one grey level of the CPU's, the 8-bit frames differing in under 0.1 % of their values
    (float rounding, atomic additions, the GPU's convolution algorithms)."""
    aug = WeatherAugment(["snow", "rain", PresetSource("snow-light", THIN_FIELD)], p=1.0, seed=6,
                         overrides=LIGHT)
    cpu = collate_pairs([aug(s) for s in samples[:3]])
    assert {w.source for w in cpu.weather} == {"snow", "rain", "snow-light"}  # both models
    for inputs in (samples[:3], [aug.prepare(s) for s in samples[:3]]):
        gpu = aug.apply_batch(collate_pairs(inputs).to("cuda"))
        assert gpu.weather == cpu.weather
        for name in ("image1", "image2"):
            x, y = getattr(gpu.pairs, name), getattr(cpu.pairs, name)
            assert x.device.type == "cuda" and x.dtype == y.dtype
            diff = (x.cpu() - y).abs()
            assert float(diff.max()) <= 1 / 255, name
            grey = (x.cpu() * 255).round() != (y * 255).round()
            assert float(grey.float().mean()) < 1e-3, name


# -- weather-field presets (world units) ----------------------------------------------------

#: A thin field keeps the tests fast: 5 flakes per cubic scene unit instead of snow-light's 40.
THIN_FIELD = {"density": 5}


def test_field_presets_render_in_both_paths_as_the_field_samples_them(samples):
    field = PresetSource("snow-light", THIN_FIELD)
    aug = WeatherAugment([field, PresetSource("snow", LIGHT)], p=1.0, seed=4, keep_particles=True)
    assert field.model == "field" and aug.sources[1].model == "paper"
    per_sample = [aug(s) for s in samples]
    assert {s.weather.source for s in per_sample} == {"snow-light", "snow"}
    for s, out in zip(samples, per_sample):
        changed = (out.pair.image1 != s.pair.image1).any(0)
        assert int(changed.sum()) > 50
        if out.weather.source == "snow-light":
            # the record is the field's, drawn from the draw's seed, with per-frame looks
            expected = sample_field_particles(s.pair, field.preset, out.weather.seed,
                                              frame_rate=DATASETS[s.pair.id.dataset].frame_rate)
            assert out.particles.optics is not None and out.particles.count > 100
            assert torch.equal(out.particles.position, expected.position)
        else:
            assert out.particles.optics is None and out.particles.count == LIGHT["count"]
    expected = collate_pairs(per_sample)
    for inputs in (samples, [aug.prepare(s) for s in samples]):
        batched = aug.apply_batch(collate_pairs(inputs))
        assert batched.weather == expected.weather
        assert torch.equal(batched.pairs.image1, expected.pairs.image1)
        assert torch.equal(batched.pairs.image2, expected.pairs.image2)


def test_the_field_ladder_keeps_its_densities(samples):
    """light, moderate and heavy snow by name: the same field tile (same seed) with 40, 120 and
    350 flakes per cubic scene unit, so the pair gets particles in that ratio."""
    counts = {}
    for name in ("snow-light", "snow-moderate", "snow-heavy"):
        prepared = WeatherAugment(name, p=1.0, seed=3).prepare(samples[0])
        assert prepared.weather.source == name and prepared.particles.optics is not None
        counts[name] = prepared.particles.count
    density = {n: load_preset(n).density for n in counts}
    for name in ("snow-moderate", "snow-heavy"):
        ratio = counts[name] / counts["snow-light"]
        assert ratio == pytest.approx(density[name] / density["snow-light"], rel=0.1), name


def test_overrides_unknown_to_a_model_are_refused(samples):
    with pytest.raises(ConfigError, match="snow-light.*'count'"):
        WeatherAugment(["snow", "snow-light"], overrides={"count": 100})


def test_keep_particles_keeps_the_rendered_record(samples):
    aug = WeatherAugment("snow", p=1.0, seed=2, overrides=LIGHT, keep_particles=True)
    out = aug(samples[0])
    assert out.particles is not None and out.particles.count == LIGHT["count"]
    batch = aug.apply_batch(collate_pairs(samples[:2]))
    assert [p.count for p in batch.particles] == [LIGHT["count"]] * 2


def test_bad_arguments_are_one_line_errors():
    with pytest.raises(ConfigError, match="probability"):
        WeatherAugment("snow", p=1.5)
    with pytest.raises(ConfigError, match="at least one preset"):
        WeatherAugment([])
    with pytest.raises(ConfigError, match="nosuch"):
        WeatherAugment(["nosuch"])
    with pytest.raises(ConfigError, match="seed"):
        WeatherAugment("snow", seed="x")
    with pytest.raises(ConfigError, match="crop size"):
        RandomCrop((0, 8))


# -- geometric augmentation after the weather ----------------------------------------------

def consistent(pair) -> float:
    """Largest gap between the pair's flow and the flow its depth and cameras imply (static
    scene), over pixels the flow marks visible in both frames."""
    implied = reprojection_flow(pair.depth1.double(), pair.intrinsics, pair.cam2_from_cam1)
    return float((implied.float() - pair.flow).abs().max())


@pytest.mark.parametrize("horizontal,vertical", [(True, False), (False, True), (True, True)])
def test_crops_and_flips_keep_flow_depth_and_cameras_consistent(samples, horizontal, vertical):
    pair = samples[0].pair
    base = consistent(pair)
    assert base < 1e-3                     # the demo scene's flow is the reprojection
    cropped = crop_pair(pair, 10, 30, 96, 200)
    assert cropped.size == (96, 200)
    assert torch.equal(cropped.image1, pair.image1[:, 10:106, 30:230])
    assert consistent(cropped) < 1e-3
    flipped = flip_pair(cropped, horizontal, vertical)
    assert consistent(flipped) < 1e-3
    flipped.validate()
    assert torch.det(flipped.cam2_from_cam1[:3, :3]) > 0


def test_weather_then_crop_and_flip_on_samples_and_on_batches(samples):
    weather = WeatherAugment("snow", p=1.0, seed=3, overrides=LIGHT)
    pipeline = Compose([weather, RandomCrop((96, 200), seed=3), RandomFlip(0.5, 0.5, seed=3)])
    per_sample = collate_pairs([pipeline(s) for s in samples])
    batched = pipeline.apply_batch(collate_pairs(samples))
    assert per_sample.pairs.image1.shape == (len(samples), 3, 96, 200)
    assert torch.equal(batched.pairs.image1, per_sample.pairs.image1)
    assert torch.equal(batched.pairs.flow, per_sample.pairs.flow)
    # the crop and flip of a weather frame is the weather frame cropped and flipped
    rendered = weather(samples[0])
    assert torch.equal(pipeline(samples[0]).pair.image2,
                       RandomFlip(0.5, 0.5, seed=3)(RandomCrop((96, 200), seed=3)(rendered)).pair.image2)
    # different samples get different windows
    crops = {tuple(pair_of(per_sample.pairs, k).intrinsics[:2, 2].tolist()) for k in range(len(samples))}
    assert len(crops) > 1


def test_crop_larger_than_the_frames_is_refused(samples):
    with pytest.raises(ShapeError, match="smaller than"):
        RandomCrop((400, 400))(samples[0])
