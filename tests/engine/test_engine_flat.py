"""weathergen.engine.flat: the ragged, fixed-operation-count forward renderer against the renderer."""

from __future__ import annotations

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from engine_scenes import plane_pair, pose, rotation
from weathergen.datasets import frame_rate_of
from weathergen.engine import load_preset, render, sample_field_particles, sample_particles
from weathergen.engine.flat import render_flat
from weathergen.framepair import FramePairBatch


def scene(i: int, dtype=torch.float64, size=(40, 72)):
    """A plane with a near block seen by two moving cameras (particles near and far)."""
    cam1 = pose(rotation(roll_deg=2, pitch_deg=-3 + i))
    cam2 = pose(rotation(roll_deg=2, pitch_deg=-2 + i, yaw_deg=1), centre=(0.05, 0.0, 0.1))
    return plane_pair(*size, depth=5.0, near_block=True, cam1_from_world=cam1,
                      cam2_from_world=cam2, seed=i, dtype=dtype)


def records_for(pairs, presets, count=120):
    return [sample_particles(p, load_preset(name, {"count": count}), seed=10 + i)
            for i, (p, name) in enumerate(zip(pairs, presets))]


def both(pairs, records, **flat_options):
    """The renderer's output and render_flat's on the same batch and records."""
    b = FramePairBatch.stack(pairs)
    args = (b.image1, b.image2, b.depth1, b.depth2, b.intrinsics, b.cam1_from_world,
            b.cam2_from_world, records)
    return render(*args), render_flat(*args, **flat_options)


def assert_close(a, b, tol):
    for name in ("image1", "image2", "opacity1", "opacity2"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        assert float((x - y).abs().max()) <= tol, (name, float((x - y).abs().max()))
    assert torch.equal(a.reached, b.reached)


@pytest.mark.parametrize("presets", [("snow", "snow"), ("rain", "snow"), ("sparks", "rain"),
                                     ("fog",)], ids=["snow", "rain+snow", "sparks+rain", "fog"])
def test_equals_the_renderer_in_float64(presets):
    """Defocused and brightened stamps (near snow), blur samples of different counts in one call
    (rain's 20, snow's 1), glows and fog's large alpha billboards on coarse grids."""
    pairs = [scene(i) for i in range(len(presets))]
    records = records_for(pairs, presets)
    a, b = both(pairs, records)
    assert bool((a.image1 != pairs[0].image1[None]).any())          # the weather is there
    assert_close(a, b, 1e-9)


def test_defocus_and_coarse_grids_are_exercised():
    """The equality above covers the blur and the coarse grids: the records hold defocused
    particles and billboards wide enough for a coarse grid."""
    pairs = [scene(0), scene(1)]
    snow, fog = records_for(pairs, ("snow", "fog"))
    assert int((snow.defocus > 1).sum()) > 0
    lib_res = 128
    assert float((fog.scale * lib_res).max()) >= 128


def test_float32_within_a_fraction_of_a_grey_level():
    pairs = [scene(i, torch.float32) for i in range(3)]
    records = records_for(pairs, ("snow", "rain", "sparks"))
    a, b = both(pairs, records)
    assert_close(a, b, 1e-3)


def test_chunks_do_not_change_the_frames():
    pairs = [scene(i) for i in range(2)]
    records = records_for(pairs, ("snow", "rain"))
    b = FramePairBatch.stack(pairs)
    args = (b.image1, b.image2, b.depth1, b.depth2, b.intrinsics, b.cam1_from_world,
            b.cam2_from_world, records)
    whole = render_flat(*args, chunk_elements=1 << 24)
    small = render_flat(*args, chunk_elements=3000)
    assert_close(whole, small, 1e-12)


def test_particles_behind_the_camera_or_outside_the_frame_reach_nothing():
    pairs = [scene(0), scene(1)]
    records = records_for(pairs, ("snow", "snow"))
    gone = records[1].replace(position=records[1].position + torch.tensor([0.0, 0.0, -50.0]))
    a, b = both(pairs, [records[0], gone])
    assert b.reached.tolist() == [True, False]
    assert torch.equal(b.image1[1], pairs[1].image1.clamp(0, 1))
    assert_close(a, b, 1e-9)


class Counter(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.ops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.ops += 1
        return func(*args, **(kwargs or {}))


def test_operation_count_does_not_grow_with_particles_or_pairs():
    """What the fast batch path is for: the number of tensor operations (kernel launches on a
    GPU) stays the same for ten times the particles and twice the pairs; the renderer's grows."""
    counts = {}
    for n, pairs in ((40, 2), (400, 2), (400, 4)):
        scenes = [scene(i) for i in range(pairs)]
        records = records_for(scenes, ["snow"] * pairs, count=n)
        b = FramePairBatch.stack(scenes)
        args = (b.image1, b.image2, b.depth1, b.depth2, b.intrinsics, b.cam1_from_world,
                b.cam2_from_world, records)
        for name, fn in (("flat", render_flat), ("render", render)):
            fn(*args)                       # the first call builds the template atlas (cached)
            counter = Counter()
            with counter:
                fn(*args)
            counts[name, n, pairs] = counter.ops
    flat = [counts["flat", n, p] for n, p in ((40, 2), (400, 2), (400, 4))]
    assert max(flat) - min(flat) <= 10, flat         # a few per-record host values at most
    assert max(flat) < 1000, flat                    # "under a thousand" (README)
    assert counts["render", 400, 4] > 2 * max(flat), counts
    # weather fields: the same, for a field four times as dense
    field = []
    for density in (4.0, 16.0):
        scenes = [scene(i) for i in range(2)]
        records = field_records(scenes, ["snow-light"] * 2, density=density)
        b = FramePairBatch.stack(scenes)
        args = (b.image1, b.image2, b.depth1, b.depth2, b.intrinsics, b.cam1_from_world,
                b.cam2_from_world, records)
        counter = Counter()
        with counter:
            render_flat(*args)
        field.append(counter.ops)
    assert max(field) - min(field) <= 10 and max(field) < 1000, field


def field_records(pairs, presets, density=8.0, **overrides):
    return [sample_field_particles(p, load_preset(name, {"density": density, **overrides}),
                                   seed=20 + i, frame_rate=frame_rate_of(p.id.dataset))
            for i, (p, name) in enumerate(zip(pairs, presets))]


@pytest.mark.parametrize("presets,overrides", [
    (("snow-light", "snow-light"), {}), (("snow-light",), {"aperture": 0.2}),
    (("rain-light",), {}), (("sparks-light",), {}), (("fog-light",), {"density": 0.5})],
    ids=["snow-light", "snow-light-defocused", "rain-light", "sparks-light", "fog-light"])
def test_weather_field_records_equal_the_per_frame_renderer(presets, overrides):
    """Field records look different in each frame (footprint f d / z, depth fade, thin-lens
    defocus, the view mask, softer occlusion): render_flat draws them as the per-frame
    renderer does, every pair and frame in the same few operations."""
    pairs = [scene(i) for i in range(len(presets))]
    records = field_records(pairs, presets, **overrides)
    assert all(r.optics is not None and r.count > 0 for r in records)
    a, b = both(pairs, records)
    assert bool((b.image1 != FramePairBatch.stack(pairs).image1).any())
    for name in ("image1", "image2", "opacity1", "opacity2"):
        x, y = getattr(a, name), getattr(b, name)
        assert float((x - y).abs().max()) <= 1e-9, (name, float((x - y).abs().max()))


def test_field_and_paper_records_in_one_call():
    pairs = [scene(0), scene(1)]
    paper = records_for(pairs[:1], ("snow",))[0]
    field = field_records(pairs[1:], ("snow-light",))[0]
    a, b = both(pairs, [paper, field])
    for name in ("image1", "image2", "opacity1", "opacity2"):
        assert float((getattr(a, name) - getattr(b, name)).abs().max()) <= 1e-9, name


def test_records_without_particles_leave_their_frames_unchanged():
    from weathergen.engine import empty_particles
    pairs = [scene(0), scene(1)]
    records = records_for(pairs, ("snow", "snow"))
    empty = empty_particles(settings=records[1].settings)
    a, b = both(pairs, [records[0], empty])
    assert_close(a, b, 1e-9)
    assert b.reached.tolist() == [True, False]
    assert torch.equal(b.image2[1], pairs[1].image2.clamp(0, 1))
    a, b = both(pairs, [empty, empty])
    assert_close(a, b, 0.0)
    assert not bool(b.reached.any())
