"""The render core against the naive oracle (tests/engine/oracle.py): outputs within 1e-9 in
float64 for every preset family of both weather models, and gradients under a random upstream
gradient; float64 gradcheck of what the oracle tests leave out (field records, occlusion
detached)."""

from __future__ import annotations

import pytest
import torch

from engine_scenes import HAZE_WISPS, plane_pair, pose, rotation
from oracle import oracle_render
from weathergen.datasets import frame_rate_of
from weathergen.engine import (BETA_ATTACK, BETA_RENDER, list_presets, load_preset,
                               load_templates, render, sample_field_particles, sample_particles)
from weathergen.engine.rendering.stamps import build
from weathergen.engine.rendering.tracks import Views, pair_tracks, streak_samples
from weathergen.framepair import FramePairBatch


def scene(i: int, size=(24, 32), depth=5.0):
    """A plane with a near block seen by two moving cameras (particles near and far)."""
    cam1 = pose(rotation(roll_deg=2, pitch_deg=-3 + i))
    cam2 = pose(rotation(roll_deg=2, pitch_deg=-2 + i, yaw_deg=1), centre=(0.05, 0.0, 0.1))
    return plane_pair(*size, depth=depth, near_block=True, cam1_from_world=cam1,
                      cam2_from_world=cam2, seed=i, dtype=torch.float64)


def paper(pair, name, seed, count=8, **overrides):
    """A few particles of a paper preset, sized for a small frame, defocus radii at most 4 (the
    oracle's disc blur is a loop over every tap)."""
    record = sample_particles(pair, load_preset(name, {"count": count, **overrides}), seed=seed)
    return record.replace(defocus=record.defocus.clamp(max=4))


def field(pair, name, seed, **overrides):
    return sample_field_particles(pair, load_preset(name, overrides), seed=seed,
                                  frame_rate=frame_rate_of(pair.id.dataset))


def arguments(pairs, records):
    b = FramePairBatch.stack(pairs)
    return (b.image1, b.image2, b.depth1, b.depth2, b.intrinsics, b.cam1_from_world,
            b.cam2_from_world, records)


def assert_equal_to_oracle(pairs, records, beta=BETA_RENDER, **options):
    args = arguments(pairs, records)
    lib = load_templates(records[0].settings.templates)
    core = render(*args, lib, beta=beta, **options)
    want = oracle_render(*args, lib, beta=beta, **options)
    for name, w in zip(("image1", "image2", "opacity1", "opacity2"), want):
        got = getattr(core, name)
        assert got.dtype == torch.float64
        assert float((got - w).abs().max()) <= 1e-9, (name, float((got - w).abs().max()))
    assert bool((core.image1 != args[0]).any())                  # the weather is there
    return core


PAPER = {"snow": {"size": 15}, "rain": {"size": 11, "blur_samples": 5},
         "sparks": {"size": 11, "blur_samples": 4}, "fog": {"count": 2},
         "additive-color": {"size": 9}, "alpha-white": {"size": 9},
         "size-large": {"size": 21}, "motion-blur-0.15": {"size": 9, "blur_samples": 3}}


@pytest.mark.parametrize("name", sorted(PAPER))
def test_paper_presets_equal_the_oracle(name):
    """Snow (defocused and brightened near flakes), rain and sparks (blur samples along a
    camera-space streak, glows), fog (large alpha billboards on a coarse grid), both blend
    modes; two pairs in one call."""
    pairs = [scene(0), scene(1)]
    over = dict(PAPER[name])
    count = over.pop("count", 8)
    records = [paper(p, name, 10 + i, count, **over) for i, p in enumerate(pairs)]
    assert_equal_to_oracle(pairs, records)


def test_the_paper_cases_cover_defocus_blur_samples_and_coarse_grids():
    """The equalities above are worth something only if the scenes hold what they claim."""
    pairs = [scene(0), scene(1)]
    snow = [paper(p, "snow", 10 + i, size=15) for i, p in enumerate(pairs)]
    assert any(int((r.defocus > 1).sum()) > 0 for r in snow)
    rain = paper(pairs[0], "rain", 10, size=11, blur_samples=5)
    assert rain.settings.blur_samples == 5 and rain.settings.blur_length > 0
    fog = paper(pairs[0], "fog", 10, 2)
    assert float((fog.scale * load_templates("dust").resolution).max()) >= 128   # coarse grid


def test_exact_large_billboards_equal_the_oracle():
    """``coarse_side=None``: every stamp on the image grid."""
    pairs = [scene(0)]
    records = [paper(pairs[0], "fog", 3, 2, size=61)]
    assert_equal_to_oracle(pairs, records, coarse_side=None)


def test_fog_across_a_depth_edge_equals_the_oracle():
    """Fog billboards between the near block (depth 1) and the plane (5) on a 2x coarser grid:
    drawn against each footprint's nearest and farthest depth and taken pixel by pixel by depth
    rank (the oracle's loops), outputs and gradients."""
    from test_engine_coarse import core_sums
    pairs = [scene(0, size=(16, 20))]
    records = [paper(pairs[0], "fog", 5, 3, size=41)]
    sums = core_sums(pairs[0], records[0], depth_aware=True, dtype=torch.float64,
                     coarse_side=24)
    level = sums.grids.levels[0][0]                  # (coarsest first)
    grid = sums.grids.planes(sums.values, 0)
    assert level == 1 and bool(((grid[0, 2:] - grid[0, :2]).abs() > 1e-3).any())   # an edge
    assert_equal_to_oracle(pairs, records, coarse_side=24)
    got, expected = core_and_oracle_gradients(pairs, records, coarse_side=24)
    assert_gradients_equal(got, expected)


FIELD = [n for n in list_presets("field")]
def test_long_streaks_get_more_blur_samples_and_equal_the_oracle():
    """Streaks longer than the preset's samples cover one pixel apart get more samples (up to
    the cap), θ / K_t each: the oracle counts them its own way (the pixel speed at the nearer
    end)."""
    pairs = [scene(0), scene(1)]
    records = [paper(p, "rain", 10 + i, 6, size=9, blur_samples=3, blur_length=1.5)
               for i, p in enumerate(pairs)]
    args = arguments(pairs, records)
    views = Views.of(torch.cat((args[4], args[4])), torch.cat((args[5], args[6])),
                     torch.cat((args[2], args[3])))
    _, tracks = pair_tracks(records, views, 80, beta=BETA_RENDER, dtype=torch.float64)
    samples, _ = streak_samples(tracks)
    assert int(samples.max()) > 6 and int(samples.min()) >= 3
    assert_equal_to_oracle(pairs, records)


def test_softened_streaks_space_their_samples_by_the_stamps_smoothness_and_equal_the_oracle():
    """A brightened defocused stamp is softened by a b x b box twice: its blur samples lie up to
    (b − 1) / 2 pixels apart (fewer samples than the one-pixel rule gives); the oracle derives
    the gap from the particle's looks its own way."""
    pairs = [scene(0)]
    record = paper(pairs[0], "sparks", 12, 6, size=7, blur_samples=3, blur_length=6.0)
    record = record.replace(defocus=torch.full_like(record.defocus, 4))   # box 7: gap 3 px
    assert record.settings.defocus_brighten
    args = arguments(pairs, [record])
    views = Views.of(torch.cat((args[4], args[4])), torch.cat((args[5], args[6])),
                     torch.cat((args[2], args[3])))
    lib = load_templates(record.settings.templates)
    looks, tracks = pair_tracks([record], views, lib.resolution, beta=BETA_RENDER,
                                dtype=torch.float64)
    stamps = build(looks, lib, dtype=torch.float64)
    assert torch.equal(stamps.gap, torch.full((looks.count,), 3.0, dtype=torch.float64))
    one_pixel, _ = streak_samples(tracks)
    spaced, _ = streak_samples(tracks, stamps.gap)
    longer = one_pixel > 2 * tracks.samples
    assert int(longer.sum()) > 0
    assert bool((spaced[longer] < one_pixel[longer]).all())
    assert_equal_to_oracle(pairs, [record])


#: Densities (and blur samples) that keep the oracle quick on a 24 x 32 frame: a dozen or two
#: particles.
#: Fog and mist are the air itself: drawn here as its uniform extinction (the oracle integrates
#: uniform air; heterogeneous air has a test of its own, against a fine reference), with wisps
#: of haze as particles in it (alpha-blended clouds on coarse grids).
AIR = {**HAZE_WISPS, "density": 0.6, "visibility": "20", "heterogeneity": "0"}
THIN = {"snow": {"density": 10.0, "snow_rate": 20.0},
        "rain": {"density": 10.0, "blur_samples": 4, "rain_rate": 200.0},
        "sparks": {"density": 10.0, "blur_samples": 3}, "fog": AIR, "mist": AIR}


# The light rung and mist of every weather in the quick tests, the other rungs (the same code at
# other densities) with the slow ones.
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow)
                                  if n.endswith(("-moderate", "-heavy")) else n for n in FIELD])
def test_field_presets_equal_the_oracle(name):
    """Per-frame looks: footprint f d / z, depth fade, the view mask, softer occlusion, streaks
    along the particle's own motion; coarse grids for fog clouds; every particle and the scene
    seen through the preset's air (strong here: visibilities of 20 to 100 m)."""
    pairs = [scene(0), scene(1)]
    records = [field(p, name, 20 + i, **THIN[name.split("-")[0]]) for i, p in enumerate(pairs)]
    assert all(r.count > 0 for r in records)
    assert all((r.atmosphere is not None) == (not name.startswith("sparks")) for r in records)
    assert_equal_to_oracle(pairs, records)


def test_defocused_field_and_a_mix_of_both_models_equal_the_oracle():
    pairs = [scene(0), scene(1), scene(2)]
    records = [field(pairs[0], "snow-light", 4, density=10.0, aperture=0.2, focus=0.5),
               paper(pairs[1], "sparks", 5, size=11, blur_samples=3),
               field(pairs[2], "rain-light", 6, density=10.0, blur_samples=4)]
    assert int(torch.cat([r.count * torch.ones(1) for r in records]).min()) > 0
    core = assert_equal_to_oracle(pairs, records)
    assert core.reached.tolist() == [True, True, True]


# -- gradients ------------------------------------------------------------------------------

FREE = ("offset1", "offset2", "color", "transparency")


def core_and_oracle_gradients(pairs, records, beta=BETA_ATTACK, **options):
    """Gradients of both renderers' outputs, under one random upstream gradient, with respect
    to every record's offsets, colour and transparency."""
    gen = torch.Generator().manual_seed(5)
    # float64 leaves: a leaf's gradient sums its uses (frame 1 and frame 2) in the leaf's type,
    # and in float32 that sum's rounding (a few 1e-8 where terms cancel) is not the renderers'
    leaves = [{n: getattr(r, n).detach().double().clone().requires_grad_(True) for n in FREE}
              for r in records]
    moved = [r.replace(**leaf) for r, leaf in zip(records, leaves)]
    args = arguments(pairs, moved)
    lib = load_templates(records[0].settings.templates)
    core = render(*args, lib, beta=beta, **options)
    core = (core.image1, core.image2, core.opacity1, core.opacity2)
    upstream = [torch.randn(c.shape, generator=gen, dtype=torch.float64) for c in core]
    flat = [t for leaf in leaves for t in leaf.values()]
    got = torch.autograd.grad(sum((c * g).sum() for c, g in zip(core, upstream)), flat,
                              allow_unused=True)
    want = oracle_render(*args, lib, beta=beta, grad=True, **options)
    expected = torch.autograd.grad(sum((w * g).sum() for w, g in zip(want, upstream)), flat,
                                   allow_unused=True)
    return got, expected


def assert_gradients_equal(got, expected):
    for g, e in zip(got, expected):
        g = torch.zeros_like(e) if g is None else g
        e = torch.zeros_like(g) if e is None else e
        torch.testing.assert_close(g, e, atol=1e-8, rtol=1e-6)
    assert sum(float(g.abs().sum()) for g in got if g is not None) > 0


@pytest.mark.parametrize("name,overrides", [("snow", {"size": 9}), ("rain", {"size": 7,
                                            "blur_samples": 3}), ("fog", {"count": 1})],
                         ids=["snow", "rain", "fog"])
def test_paper_gradients_equal_the_oracle(name, overrides):
    pair = scene(0, size=(12, 16))
    over = dict(overrides)
    count = over.pop("count", 3)
    got, expected = core_and_oracle_gradients([pair], [paper(pair, name, 2, count, **over)])
    assert_gradients_equal(got, expected)


def test_field_gradients_equal_the_oracle():
    pair = scene(0, size=(12, 16))
    record = field(pair, "rain-light", 3, density=40.0, blur_samples=3)
    assert record.count > 0
    got, expected = core_and_oracle_gradients([pair], [record.select(torch.arange(4))])
    assert_gradients_equal(got, expected)


def test_detached_occlusion_equals_the_oracle_with_a_constant_depth():
    """``detach_occlusion``: no gradient through the visibility term; the rest unchanged."""
    pair = scene(0, size=(12, 16), depth=1.6)          # particles near the plane: V matters
    record = paper(pair, "snow", 4, 3, size=9)
    got, expected = core_and_oracle_gradients([pair], [record], detach_occlusion=True)
    assert_gradients_equal(got, expected)
    full, _ = core_and_oracle_gradients([pair], [record])
    assert not torch.allclose(full[0], got[0])          # the occlusion term did contribute


def test_gradcheck_of_a_field_record():
    """Colour and transparency (a field particle's looks follow its detached position, so the
    offsets' derivative is checked against the oracle above, which detaches them too)."""
    pair = scene(0, size=(10, 12))
    record = field(pair, "snow-light", 3, density=40.0).select(torch.arange(3))
    lib = load_templates(record.settings.templates)
    g = torch.Generator().manual_seed(1)
    weights = torch.rand(6, 2 * 4 * 10 * 12, generator=g, dtype=torch.float64)

    def f(col, th):
        args = arguments([pair], [record.replace(color=col, transparency=th)])
        o = render(*args, lib, beta=BETA_ATTACK)
        flat = torch.cat([t.reshape(-1) for t in (o.image1, o.image2, o.opacity1, o.opacity2)])
        return weights @ flat

    leaves = [getattr(record, n).double().clone().requires_grad_(True)
              for n in ("color", "transparency")]
    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-6)


def test_combined_weather_equals_the_layered_oracle():
    """Snow and fog of the paper's model and weather fields in one pass: each layer's sums
    with its own templates, composited per pixel far to near by the layers' mean depths, the
    scene and every particle seen through the composed air of the rain's veil and a fog."""
    from oracle import oracle_layered
    from weathergen.engine import LayeredParticles

    pairs = [scene(0), scene(1)]
    # The rain thinned as in test_field_presets_equal_the_oracle (still hundreds of drops over
    # the snow and fog of each frame): the oracle's time grows with drops x streak samples.
    layered = [LayeredParticles((paper(p, "snow", 20 + i, 6, size=15, blend="alpha"),
                                 paper(p, "fog", 30 + i, 2),
                                 field(p, "rain-light", 40 + i, **THIN["rain"]),
                                 field(p, "fog-heavy", 0, heterogeneity=0.0, visibility=30.0)),
                                ("snow", "fog", "rain-light", "fog-heavy"))
               for i, p in enumerate(pairs)]
    assert all(stack.layer(2).count > 100 for stack in layered)
    args = arguments(pairs, layered)
    core = render(*args, beta=BETA_RENDER)
    want = oracle_layered(*args, beta=BETA_RENDER)
    for name, w in zip(("image1", "image2", "opacity1", "opacity2"), want):
        got = getattr(core, name)
        assert float((got - w).abs().max()) <= 1e-9, (name, float((got - w).abs().max()))
    assert bool((core.image1 != args[0]).any())
