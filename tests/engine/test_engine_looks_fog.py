"""Looks measured on scenes made here: the fog presets (atmospheres) and wisps of haze drawn as
particles read as haze without steps, and wisps stay behind nearer geometry; an out-of-focus
flake is a soft disc carrying the light the paper's brightening rule gives it.

Scenes: a KITTI-like frame (1242 x 375, f = 721) of a textured plane at 30 m with a wall at 5 m
over its left half (``engine_scenes.wall_scene``); isolated white flakes on a black plane far
behind them (additive, θ = 1, so a pixel's opacity is the stamp's value there).
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from engine_scenes import HAZE_WISPS, plane_pair, wall_scene
from weathergen.engine import (Particles, RenderSettings, build_stamps, load_preset,
                               load_templates, render_pair, sample_weather)
from weathergen.engine.sampling.pair import defocus_radius
from weathergen.engine.weather.templates import HAZE_ALPHA_RANGE, HAZE_MAX_SLOPE, _disc_mask

KITTI = dict(size=(375, 1242), focal=721.0, plane_depth=30.0, wall_depth=5.0, wall_columns=620)
EDGE = slice(600, 640)            # the wall's edge: a depth step, where fog may stop abruptly
FOG = ["fog-light", "fog-moderate", "fog-heavy"]


def fog_record(pair, name, seed=0, **overrides):
    return sample_weather(pair, load_preset(name, overrides), seed, frame_rate=10.0)


def largest_step(opacity: torch.Tensor) -> float:
    """Largest change between 4-neighbours, the wall's edge left out. Shape: (H, W)."""
    dx = (opacity[:, 1:] - opacity[:, :-1]).abs()
    dy = (opacity[1:] - opacity[:-1]).abs()
    dx[:, EDGE], dy[:, EDGE] = 0, 0
    return max(float(dx.max()), float(dy.max()))


def radial_profile(opacity: torch.Tensor, cx: float, cy: float, bins: int, reach: float):
    """Mean opacity in ``bins`` rings of equal width from the centre out to ``reach`` px."""
    h, w = opacity.shape
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                            torch.arange(w, dtype=torch.float64), indexing="ij")
    ring = torch.floor(torch.hypot(xx - cx, yy - cy) / (reach / bins)).long().flatten()
    keep = ring < bins
    total = torch.bincount(ring[keep], opacity.flatten().double()[keep], minlength=bins)
    return total / torch.bincount(ring[keep], minlength=bins).clamp(min=1)


def clouds_at(pair, record, u, v, z, index):
    """Clouds ``index`` of ``record`` moved so that their centres project to (u, v) at depth
    z (lists of floats, one per cloud)."""
    k = pair.intrinsics
    pos = torch.tensor([[(a - float(k[0, 2])) / float(k[0, 0]) * c,
                         (b - float(k[1, 2])) / float(k[1, 1]) * c, c]
                        for a, b, c in zip(u, v, z)], dtype=torch.float64)
    some = record.select(torch.tensor(index))
    return some.replace(position=pos.to(some.position.dtype))


def cloud_at(pair, record, u: float, v: float, z: float, index: int = 0):
    """One cloud of ``record`` moved so that its centre projects to (u, v) at depth z."""
    return clouds_at(pair, record, [u], [v], [z], [index])


def test_haze_templates_fall_to_zero_at_the_rim_without_an_outline():
    """Each ``haze`` template: mean alpha about a third inside its disc, its alpha changing by at
    most HAZE_MAX_SLOPE per unit of radius anywhere, and its outer ring (the last 2 % of the
    radius) below 0.005: no body, no rim."""
    lib = load_templates("haze")
    res = lib.resolution
    inside = _disc_mask(res)
    c = (res - 1) / 2
    yy, xx = torch.meshgrid(torch.arange(res, dtype=torch.float64),
                            torch.arange(res, dtype=torch.float64), indexing="ij")
    r = torch.hypot(xx - c, yy - c) / (res / 2)
    lo, hi = HAZE_ALPHA_RANGE
    for a in lib.alphas.double():
        assert lo <= float(a[torch.from_numpy(inside)].mean()) <= hi
        slope = max(float((a[:, 1:] - a[:, :-1]).abs().max()),
                    float((a[1:] - a[:-1]).abs().max())) * res / 2
        assert slope <= HAZE_MAX_SLOPE, slope
        assert float(a[r >= 0.98].max()) < 0.005


@pytest.mark.parametrize("name", FOG)
@pytest.mark.parametrize("wisps", [False, True])
def test_field_fog_is_haze_without_steps(name, wisps):
    """Over a whole frame of each fog preset (the air itself, its banks), and of wisps of haze
    drawn as particles at the density of the fog presets before they became atmospheres
    (0.01, 0.03, 0.075 per m³), on three seeds, no two neighbouring pixels of ``opacity1``
    differ by more than 1/64 away from the wall's edge (the earlier clouds' flat bodies and
    smoothstep rims gave steps of 0.10-0.16)."""
    pair = wall_scene(**KITTI)
    density = {"fog-light": "0.01", "fog-moderate": "0.03", "fog-heavy": "0.075"}[name]
    for seed in range(3):
        record = fog_record(pair, name, seed, **({**HAZE_WISPS, "density": density}
                                                  if wisps else {}))
        opacity = render_pair(pair, record).opacity1[0, 0].double()
        assert float(opacity[:, 640:].mean()) > 0.02               # there is fog to measure
        assert largest_step(opacity) <= 1 / 64, (seed, largest_step(opacity))


def test_an_isolated_fog_cloud_has_no_outline():
    """A wisp of haze alone over the open plane: its radial profile falls from the centre to the rim
    with no step (each of 12 rings below the last, the steepest fall at most twice the mean
    fall), not a flat disc that drops at its rim."""
    pair = wall_scene(**KITTI)
    record = fog_record(pair, "fog-moderate", **HAZE_WISPS)
    for z in (6.0, 12.0, 20.0):
        for index in range(3):
            one = cloud_at(pair, record, 930.0, 187.0, z, index)
            opacity = render_pair(pair, one).opacity1[0, 0].double()
            footprint = 721.0 * float(one.scale[0]) / z
            profile = radial_profile(opacity, 930.0, 187.0, 12, footprint / 2)
            drops = profile[:-1] - profile[1:]
            assert bool((drops > 0).all()), (z, profile)
            mean_drop = float(profile[0] - profile[-1]) / (len(profile) - 1)
            assert float(drops.max()) <= 2 * mean_drop, (z, profile)


def test_field_fog_stays_behind_a_nearer_wall():
    """Wisps of haze 1 m behind the wall, their centres just past its edge so that their billboards
    reach over it: alone, each adds at most 0.005 opacity over the wall; a dozen together
    1-3 m behind it also at most 0.005 (the old symmetric softness of 0.5 m let 0.028 and 0.019
    through)."""
    pair = wall_scene(**KITTI)
    g = torch.Generator().manual_seed(1)
    for name, density in zip(FOG, ("0.01", "0.03", "0.075")):
        record = fog_record(pair, name, **{**HAZE_WISPS, "density": density}) \
            .select(torch.arange(12))
        u = (630 + 60 * torch.rand(12, generator=g, dtype=torch.float64)).tolist()
        v = (375 * torch.rand(12, generator=g, dtype=torch.float64)).tolist()
        for i in range(12):
            one = cloud_at(pair, record, u[i], v[i], 6.0, i)
            over_wall = render_pair(pair, one).opacity1[0, 0, :, :590]
            assert float(over_wall.max()) <= 0.005, (name, i, float(over_wall.max()))
        z = (6 + 2 * torch.rand(12, generator=g, dtype=torch.float64)).tolist()
        together = clouds_at(pair, record, u, v, z, list(range(12)))
        reach = render_pair(pair, together).opacity1[0, 0]
        assert float(reach[:, 640:].max()) > 0.02                   # they are there ...
        assert float(reach[:, :590].max()) <= 0.005                 # ... but not over the wall


# -- out-of-focus flakes ---------------------------------------------------------------------

H, W, CELL = 436, 1024, 128


def flakes_at(depths, seed: int = 3):
    """White snow flakes (θ = 1), one per 128-px cell, at the given camera depths: size and
    defocus radius from the paper's formulas, random templates, rotations and sub-pixel
    positions. Returns (pair, particles, centres (N, 2))."""
    pair = plane_pair(H, W, depth=50.0, world=False, dtype=torch.float64)
    pair.image1 = torch.zeros_like(pair.image1)
    pair.image2 = torch.zeros_like(pair.image2)
    preset = load_preset("snow")
    lib = load_templates(preset.templates)
    g = torch.Generator().manual_seed(seed)
    n, cols = len(depths), W // CELL
    idx = torch.arange(n)
    u = (idx % cols).double() * CELL + CELL / 2 + torch.rand(n, generator=g, dtype=torch.float64)
    v = (idx // cols).double() * CELL + CELL / 2 + torch.rand(n, generator=g, dtype=torch.float64)
    d = torch.tensor(depths, dtype=torch.float64)
    k = pair.intrinsics
    pos = torch.stack(((u - k[0, 2]) * d / k[0, 0], (v - k[1, 2]) * d / k[1, 1], d), 1)
    footprint = preset.size * torch.clamp(1 / (d * preset.depth_decay), max=1)
    zeros = torch.zeros(n, 3, dtype=torch.float64)
    parts = Particles(
        position=pos, motion=zeros, offset1=zeros, offset2=zeros,
        color=torch.ones(n, 3, dtype=torch.float64), transparency=torch.ones(n, dtype=torch.float64),
        template=torch.randint(0, lib.count, (n,), generator=g),
        rotation=torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi,
        scale=footprint / lib.resolution, defocus=defocus_radius(d), frame="camera1",
        settings=RenderSettings.from_preset(preset, lib).replace(blend="additive"))
    return pair, parts, torch.stack((u, v), 1)


def rule_light(parts: Particles, j: int) -> float:
    """The light the brightening rule gives particle j, computed here from its stamp in focus
    (the renderer's, defocus 0: the template sampled at the footprint): blurred by the disc of
    its defocus radius (taps with dx² + dy² <= r²), then ``Σ min(1, (2 b)^(1/3))``."""
    lib = load_templates(parts.settings.templates)
    one = parts.select(torch.tensor([j]))
    sharp = build_stamps([one.replace(defocus=torch.zeros_like(one.defocus))], lib,
                         dtype=torch.float64)
    side = int(sharp.side[0])
    stamp = sharp.pixels[:(side + 2) ** 2].view(side + 2, side + 2)
    r = int(parts.defocus[j])
    o = torch.arange(-r, r + 1, dtype=torch.float64)
    disc = ((o[:, None] ** 2 + o[None, :] ** 2) <= r * r).double()
    b = F.conv2d(stamp[None, None], (disc / disc.sum())[None, None], padding=2 * r)[0, 0]
    return float(torch.clamp(2 * b, min=0).pow(1 / 3).clamp(max=1).sum())


def test_an_out_of_focus_flake_is_a_soft_disc_with_the_rules_light():
    """Snowflakes at depths 0.6-0.8 (defocus radius 4-20 px): each one's radial profile (1-px
    rings around its projected centre) never rises, its steepest 1-px fall is at most 0.15 of
    its peak (a hard rim fell by 0.2-0.3), and its total light is within 5 % of the rule's."""
    depths = [0.8, 0.75, 0.7, 0.65, 0.6] * 4
    pair, parts, centres = flakes_at(depths)
    radii = parts.defocus.tolist()
    assert min(radii) >= 4 and max(radii) == 20
    opacity = render_pair(pair, parts).opacity1[0, 0]
    cols = W // CELL
    for j in range(parts.count):
        r0, c0 = (j // cols) * CELL, (j % cols) * CELL
        cell = opacity[r0:r0 + CELL, c0:c0 + CELL].double()
        cx, cy = float(centres[j, 0]) - c0, float(centres[j, 1]) - r0
        reach = int(math.ceil(float(cell.nonzero().sub(torch.tensor([cy, cx])).norm(dim=1).max())))
        profile = radial_profile(cell, cx, cy, reach + 1, reach + 1.0)
        peak = float(profile.max())
        drops = profile[:-1] - profile[1:]
        assert float(drops.min()) >= -0.01 * peak, (depths[j], radii[j], profile)
        assert float(drops.max()) <= 0.15 * peak, (depths[j], radii[j], float(drops.max()) / peak)
        light, want = float(cell.sum()), rule_light(parts, j)
        assert abs(light - want) <= 0.05 * want, (depths[j], radii[j], light, want)
