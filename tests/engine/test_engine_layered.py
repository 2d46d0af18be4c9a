"""Combined weather rendered in one pass (weathergen/engine/rendering/combined.py): depth order between the
layers on a hand-made scene, the layered composite's gradient, a single layer's bytes, batches."""

from __future__ import annotations

from typing import Optional, Sequence

import pytest
import torch

from engine_scenes import plane_pair, wisps
from weathergen.engine import (BETA_ATTACK, BETA_RENDER, LayeredParticles, build_stamps,
                               load_preset, load_templates, render, render_pair,
                               sample_particles, sample_weather)
from weathergen.engine.rendering.composite import _LayeredBlend
from weathergen.framepair import FramePairBatch
from weathergen.errors import ConfigError

RED, BLUE = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)


class GridLayout:
    """Planes given whole, ``(5, T, B, L, 1, H, W)`` (:func:`composite_layers`)."""

    def read(self, values: Sequence[torch.Tensor], t: int, k: int,
             channels: Optional[int] = None) -> torch.Tensor:
        return values[0][:channels, t, :, k, 0]

    def gradients(self, values: Sequence[torch.Tensor]) -> list:
        return [torch.zeros_like(values[0])]

    def buffer(self, g_values: Sequence[torch.Tensor], t: int, k: int) -> torch.Tensor:
        return g_values[0][:4, t, :, k, 0]

    def finish(self, g_values, buffer, t: int, k: int) -> None:
        pass


def composite_layers(alpha: torch.Tensor, colour: torch.Tensor, depth: torch.Tensor,
                     image: torch.Tensor, alpha_mode: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """The frames of layered sums: per pixel the layers far to near by their mean depth
    ``Z / A``, each blended over the result so far with its mode, clamped once at the end.

    Shape: alpha (B, L, 1, H, W) ``A``; colour (B, L, 3, H, W) ``C``; depth (B, L, 1, H, W)
    ``Z = Σ θ B V z``; image (B, 3, H, W); alpha_mode (B, L) bool -> (image (B, 3, H, W),
    opacity (B, 1, H, W)). Differentiable in alpha, colour and image (not in the order).
    """
    grid = torch.cat((alpha, colour, depth), 2).permute(2, 0, 1, 3, 4)[:, None, :, :, None]
    out, opacity = _LayeredBlend.apply(alpha_mode, GridLayout(), 1, grid, image)
    return out, opacity


@pytest.fixture(scope="module")
def pair():
    return plane_pair(48, 64, depth=6.0, dtype=torch.float64)


def one_particle(pair, name: str, depth: float, colour, *, size: int = 31,
                 blend: str = "alpha") -> object:
    """A single opaque-ish particle of preset ``name`` (alpha blend unless ``blend``) on the
    optical axis at ``depth``, not moving, of the given colour, footprint ``size`` pixels
    whatever its depth."""
    record = sample_particles(pair, load_preset(name, {"count": 1, "blend": blend,
                                                       "motion_blur": False}), seed=1)
    z = torch.zeros_like(record.position)
    position = torch.tensor([[0.0, 0.0, depth]], dtype=record.position.dtype)
    resolution = 80 if record.settings.templates == "flakes" else 128
    return record.replace(position=position, motion=z, offset1=z, offset2=z.clone(),
                          color=torch.tensor([colour], dtype=record.color.dtype),
                          transparency=torch.ones_like(record.transparency),
                          scale=torch.full_like(record.scale, size / resolution),
                          defocus=torch.zeros_like(record.defocus))


def centre(out, name="image1"):
    image = getattr(out, name)[0]
    return image[:, image.shape[1] // 2, image.shape[2] // 2]


@pytest.mark.parametrize("near", ["snow", "fog"])
def test_the_nearer_layer_hides_the_farther_one(pair, near):
    """A near red snow flake in front of a far blue fog billboard shows red at the centre, and
    with the depths swapped the fog shows blue; the order the layers are listed in does not
    matter (bit for bit)."""
    depth = {"snow": 1.5, "fog": 4.0} if near == "snow" else {"snow": 4.0, "fog": 1.5}
    flake = one_particle(pair, "snow", depth["snow"], RED)
    cloud = one_particle(pair, "fog", depth["fog"], BLUE)
    out = render_pair(pair, LayeredParticles((flake, cloud), ("snow", "fog")))
    swapped = render_pair(pair, LayeredParticles((cloud, flake), ("fog", "snow")))
    r, _, b = centre(out).tolist()
    if near == "snow":
        assert r > b + 0.3, (r, b)
    else:
        assert b > r + 0.3, (r, b)
    for name in ("image1", "image2", "opacity1", "opacity2"):
        assert torch.equal(getattr(out, name), getattr(swapped, name)), name
    # each layer alone: the near one alone looks like the pair's centre up to what shows through
    alone = render_pair(pair, flake if near == "snow" else cloud)
    assert float((centre(alone) - centre(out)).abs().max()) < 0.25


@pytest.mark.parametrize("flake_depth", [4.0, 1.5], ids=["behind", "in-front"])
def test_an_additive_particle_behind_an_alpha_layer_is_dimmed_by_it(pair, flake_depth):
    """An additive red flake behind a blue fog billboard (depth 4 against 3) reaches the camera
    through the fog: its opacity and light are times ``T = 1 − A_fog`` read at the flake (the
    fog's opacity interpolated at its projected centre), over its whole stamp, so
    ``1 − opacity = (1 − T A_flake)(1 − A_fog)`` at every pixel; in front of the fog (depth
    1.5) ``T = 1``."""
    flake = one_particle(pair, "snow", flake_depth, RED, blend="additive")
    flake = flake.replace(transparency=torch.full_like(flake.transparency, 0.5))
    cloud = one_particle(pair, "fog", 3.0, BLUE, size=41)
    cloud = cloud.replace(transparency=torch.full_like(cloud.transparency, 0.6))
    out = render_pair(pair, LayeredParticles((flake, cloud), ("snow", "fog")))
    a_flake = render_pair(pair, flake).opacity1[0, 0]
    a_fog = render_pair(pair, cloud).opacity1[0, 0]
    assert float(a_flake.max()) < 1 and float(a_fog.max()) < 1 and float(a_fog.min()) == 0
    if flake_depth > 3.0:      # the fog at the flake's centre (cx, cy), bilinearly
        k = pair.intrinsics
        x, y = float(k[0, 2]), float(k[1, 2])
        x0, y0 = int(x), int(y)
        fx, fy = x - x0, y - y0
        at = a_fog[y0:y0 + 2, x0:x0 + 2]
        t = 1 - float((1 - fy) * ((1 - fx) * at[0, 0] + fx * at[0, 1])
                      + fy * ((1 - fx) * at[1, 0] + fx * at[1, 1]))
        assert 0.2 < t < 0.9
    else:
        t = 1.0
    want = 1 - (1 - t * a_flake) * (1 - a_fog)
    assert torch.allclose(out.opacity1[0, 0], want, atol=1e-12)
    # the light: the fog's frame plus the flake's (red) light times T, where nothing clips
    fog_frame = render_pair(pair, cloud).image1[0]
    flake_frame = render_pair(pair, flake).image1[0]
    want = fog_frame + t * (flake_frame - pair.image1)
    unclipped = (flake_frame < 1).all(0) & (want < 1).all(0)
    assert int(unclipped.sum()) > 0.9 * unclipped.numel()
    assert torch.allclose(out.image1[0][:, unclipped], want[:, unclipped], atol=1e-12)


def test_the_far_to_near_composite_is_the_over_operator(pair):
    """Where both layers cover a pixel, the image is the far layer's blend under the near
    layer's: ``(I (1 − A_f) + C_f)(1 − A_n) + C_n``, computed here by hand from two pixels."""
    a = torch.tensor([[[[[0.6]]], [[[0.5]]]]], dtype=torch.float64)            # (1, 2, 1, 1, 1)
    c = torch.tensor([[[[[0.3]], [[0.0]], [[0.0]]], [[[0.0]], [[0.0]], [[0.4]]]]],
                     dtype=torch.float64)                                        # (1, 2, 3, 1, 1)
    image = torch.full((1, 3, 1, 1), 0.5, dtype=torch.float64)
    mode = torch.tensor([[True, True]])
    for z0, z1 in ((1.0, 3.0), (3.0, 1.0)):
        z = torch.tensor([[[[[z0 * 0.6]]], [[[z1 * 0.5]]]]], dtype=torch.float64)   # Z = A d
        out, opacity = composite_layers(a, c, z, image, mode)
        far, near = (1, 0) if z0 < z1 else (0, 1)
        under = image[0, :, 0, 0] * (1 - a[0, far, 0, 0, 0]) + c[0, far, :, 0, 0]
        want = under * (1 - a[0, near, 0, 0, 0]) + c[0, near, :, 0, 0]
        assert torch.allclose(out[0, :, 0, 0], want, atol=1e-15)
        assert float(opacity) == pytest.approx(1 - 0.4 * 0.5)
    # an additive layer adds its colour wherever it lies
    out, _ = composite_layers(a, c, torch.tensor([[[[[0.6]]], [[[1.5]]]]], dtype=torch.float64),
                              image, torch.tensor([[False, True]]))
    want = (image[0, :, 0, 0] * 0.5 + c[0, 1, :, 0, 0]) + c[0, 0, :, 0, 0]
    assert torch.allclose(out[0, :, 0, 0], want, atol=1e-15)


def test_gradcheck_of_the_layered_composite():
    """float64 gradcheck on a tiny case (3 layers, distinct depths, no clamping)."""
    g = torch.Generator().manual_seed(0)
    a = (0.2 + 0.3 * torch.rand(2, 3, 1, 2, 3, generator=g, dtype=torch.float64)).requires_grad_()
    c = (0.1 * torch.rand(2, 3, 3, 2, 3, generator=g, dtype=torch.float64)).requires_grad_()
    depth = (a.detach() * torch.rand(2, 3, 1, 2, 3, generator=g, dtype=torch.float64) * 5)
    image = (0.2 + 0.3 * torch.rand(2, 3, 2, 3, generator=g, dtype=torch.float64)).requires_grad_()
    mode = torch.tensor([[True, False, True], [False, True, True]])
    assert torch.autograd.gradcheck(lambda a, c, i: composite_layers(a, c, depth, i, mode),
                                    (a, c, image))


@pytest.mark.parametrize("blends,flake_depth", [(("alpha", "alpha"), 1.5),
                                                (("additive", "alpha"), 1.5),
                                                (("additive", "alpha"), 4.0),
                                                (("additive", "additive"), 1.5)],
                         ids=["sorting-network", "additive-over-alpha", "additive-behind-alpha",
                              "additive-pair"])
def test_gradcheck_of_a_layered_render(pair, blends, flake_depth):
    """Gradients reach every layer's colours, transparencies and offsets, and the opacity's
    (float64 gradcheck on a small scene: a snow flake and a fog billboard, overlapping), for
    each form of the composite: two alpha layers (the sorting network), an additive flake in
    front of alpha fog and one behind it (dimmed by the fog at its centre: the gradient also
    reaches the fog's transparency and the flake's offset through the dimming), two additive
    layers."""
    small = plane_pair(20, 24, depth=6.0, dtype=torch.float64)
    flake = one_particle(small, "snow", flake_depth, RED, size=7, blend=blends[0])
    cloud = one_particle(small, "fog", 3.0, BLUE, size=11, blend=blends[1])
    cloud = cloud.replace(position=cloud.position + torch.tensor([[0.1, 0.05, 0.0]],
                                                                 dtype=torch.float64))
    layered = LayeredParticles((flake, cloud), ("snow", "fog"))
    stamps = build_stamps(layered, None, dtype=torch.float64)
    weights = torch.rand(4, 2, 3, 20, 24, generator=torch.Generator().manual_seed(0),
                         dtype=torch.float64)

    def run(colour, theta, offset):     # four random projections of both frames
        layers = (flake.replace(color=colour, offset1=offset), cloud.replace(transparency=theta))
        out = render_pair(small, LayeredParticles(layers, ("snow", "fog")), beta=BETA_ATTACK,
                          stamps=stamps, coarse_side=None)
        frames = torch.stack((out.image1[0], out.image2[0]))
        opacity = (out.opacity1[0] * weights[0, 0, :1] + out.opacity2[0] * weights[1, 1, :1])
        return torch.cat(((weights * frames).sum((1, 2, 3, 4)), opacity.sum()[None]))

    inputs = (flake.color.clone().double().mul(0.8).requires_grad_(),
              (cloud.transparency.double() * 0.7).requires_grad_(),
              # off the nodes of the phase stamps' piecewise-linear interpolation (a flake on
              # a pixel centre sits on one: left and right derivatives differ there)
              torch.tensor([[1.3e-3, 0.7e-3, 0.0]], dtype=torch.float64).requires_grad_())
    assert torch.autograd.gradcheck(run, inputs, atol=1e-6)


def test_one_layer_renders_its_record_bytes_and_batches_render_each_pair_alone():
    pairs = [plane_pair(40, 56, depth=5.0, seed=s) for s in (0, 1)]
    preset = load_preset("snow+fog", {"snow.count": 40, "fog.count": 3})
    layered = [sample_weather(p, preset, seed=s) for s, p in enumerate(pairs)]
    single = LayeredParticles((layered[0].layers[0],), ("snow",))
    assert torch.equal(render_pair(pairs[0], single).image1,
                       render_pair(pairs[0], layered[0].layers[0]).image1)
    batch = render_pair(FramePairBatch.stack(pairs), layered)
    for k, (p, record) in enumerate(zip(pairs, layered)):
        alone = render_pair(p, record)
        for name in ("image1", "image2", "opacity1", "opacity2"):
            assert torch.equal(getattr(batch, name)[k], getattr(alone, name)[0]), (k, name)
        assert bool((alone.image1 != p.image1).any())
    with pytest.raises(ConfigError, match="same number of weather layers"):
        render_pair(FramePairBatch.stack(pairs), [layered[0], layered[1].layers[0]])


def test_gradcheck_of_a_layered_render_with_a_coarse_grid(pair):
    """A fog billboard wide enough for a coarse grid (upsampled in the composite) under a snow
    flake: float64 gradcheck of both layers' colours and the fog's transparency."""
    flake = one_particle(pair, "snow", 1.5, RED, size=9)
    cloud = one_particle(pair, "fog", 3.0, BLUE, size=141)
    layered = LayeredParticles((flake, cloud), ("snow", "fog"))
    stamps = build_stamps(layered, None, dtype=torch.float64)
    assert int(stamps.coarse.max()) > 0                     # the billboard is drawn coarse
    assert_layered_gradcheck(pair, flake, cloud, stamps, seed=1, opacity="opacity1",
                             fog_colours=[[0.1, 0.3, 0.6]], thetas=[0.4])


def assert_layered_gradcheck(pair, flake, cloud, stamps, *, seed: int, opacity: str,
                             fog_colours, thetas) -> None:
    """float64 gradcheck of a snow-over-fog render in the snow colour, the fog colours and
    transparencies: a few random projections of both frames and one opacity."""
    weights = torch.rand(3, 2, 3, 48, 64, generator=torch.Generator().manual_seed(seed),
                         dtype=torch.float64)

    def run(snow_colour, fog_colour, theta):
        layers = (flake.replace(color=snow_colour),
                  cloud.replace(color=fog_colour, transparency=theta))
        out = render_pair(pair, LayeredParticles(layers, ("snow", "fog")), beta=BETA_ATTACK,
                          stamps=stamps)
        frames = torch.stack((out.image1[0], out.image2[0]))
        return torch.cat(((weights * frames).sum((1, 2, 3, 4)),
                          (getattr(out, opacity) * weights[0, 0, :1]).sum()[None]))

    inputs = (torch.tensor([[0.7, 0.2, 0.1]], dtype=torch.float64, requires_grad=True),
              torch.tensor(fog_colours, dtype=torch.float64, requires_grad=True),
              torch.tensor(thetas, dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(run, inputs, atol=1e-6)


def test_layers_drawn_on_coarse_grids_alone(pair):
    """Every stamp on a coarse grid (two wide fog billboards; a plain render then splats no
    image-grid plane): one such layer renders its record's bytes, and the nearer of two hides
    the farther one."""
    near = one_particle(pair, "fog", 2.0, RED, size=141)
    far = one_particle(pair, "fog", 4.0, BLUE, size=141)
    assert torch.equal(render_pair(pair, LayeredParticles((near,), ("fog",))).image1,
                       render_pair(pair, near).image1)
    out = render_pair(pair, LayeredParticles((far, near), ("far", "near")))
    red, _, blue = centre(out).tolist()
    assert red > 0.5 and red > 4 * blue


@pytest.mark.parametrize("names", [("snow", "fog"), ("fog", "snow"), ("snow", "sparks")],
                         ids=["additive-over-alpha", "listed-the-other-way", "additive-pair"])
def test_two_layer_forms_equal_the_layered_oracle(names):
    """The closed forms of two layers (an additive layer and an alpha one in either listing
    order, two additive layers) against the layered oracle within 1e-9 (float64, a batch of two
    pairs, fog drawn on a coarse grid), and the same bytes whichever layer is listed first."""
    from oracle import oracle_layered
    from test_engine_oracle import arguments, paper, scene

    pairs = [scene(0, size=(20, 28)), scene(1, size=(20, 28))]
    options = {"snow": {"size": 15}, "sparks": {"size": 11, "blur_samples": 3},
               "fog": {"count": 2}}

    layered = [LayeredParticles(tuple(paper(p, n, 10 * i + len(n), **({"count": 6} | options[n]))
                                      for n in names), names) for i, p in enumerate(pairs)]
    modes = {r.settings.blend for r in layered[0].layers}
    assert modes == ({"additive"} if "sparks" in names else {"additive", "alpha"})
    if "fog" in names:                                      # its billboards drawn coarse
        assert int(build_stamps(layered, None, coarse_side=16).coarse.max()) > 0
    args = arguments(pairs, layered)
    core = render(*args, beta=BETA_RENDER, coarse_side=16)
    want = oracle_layered(*args, beta=BETA_RENDER, coarse_side=16)
    for name, w in zip(("image1", "image2", "opacity1", "opacity2"), want):
        got = getattr(core, name)
        assert float((got - w).abs().max()) <= 1e-9, (name, float((got - w).abs().max()))
    assert bool((core.image1 != args[0]).any())
    swapped = [LayeredParticles(p.layers[::-1], p.names[::-1]) for p in layered]
    other = render(*arguments(pairs, swapped), beta=BETA_RENDER, coarse_side=16)
    for name in ("image1", "image2", "opacity1", "opacity2"):
        assert torch.equal(getattr(core, name), getattr(other, name)), name


def test_gradcheck_of_a_layer_on_both_grids(pair):
    """A fog layer with a wide billboard (drawn on a coarse grid) and a small one (on the image
    grid) under an additive flake: the layer's gradient reaches both grids (float64 gradcheck of
    the fog's colours and transparencies and the flake's colour, the opacity included)."""
    wide = one_particle(pair, "fog", 3.0, BLUE, size=141)
    small = one_particle(pair, "fog", 2.5, RED, size=15)
    small = small.replace(position=small.position + torch.tensor([[0.2, 0.1, 0.0]],
                                                                 dtype=small.position.dtype))
    cloud = wide.replace(**{name: torch.cat((getattr(wide, name), getattr(small, name)))
                            for name in ("position", "motion", "offset1", "offset2", "color",
                                         "transparency", "scale", "defocus", "rotation",
                                         "template")})
    flake = one_particle(pair, "snow", 1.5, RED, size=9, blend="additive")
    layered = LayeredParticles((flake, cloud), ("snow", "fog"))
    stamps = build_stamps(layered, None, dtype=torch.float64)
    assert sorted(stamps.coarse.tolist()) == [0, 0, 3]      # the flake, the small, the wide
    assert_layered_gradcheck(pair, flake, cloud, stamps, seed=2, opacity="opacity2",
                             fog_colours=[[0.1, 0.3, 0.6], [0.5, 0.4, 0.2]], thetas=[0.4, 0.6])


def test_where_one_layer_covers_a_pixel_it_is_that_layer_rendered_alone():
    """Each layer is drawn as its record alone: where only the alpha layer covers a pixel, the
    combined frame there is that record's frame rendered alone, bit for bit (an additive snow
    layer and an alpha one of small white particles, float32); where none does, the pair's own
    image; where only the snow covers it, farther from the white particles than a flake's stamp
    reaches, the snow layer's frame alone, and nearer than that never brighter than it (a flake
    behind a white particle is dimmed by it, over its whole stamp)."""
    pair = plane_pair(40, 56, depth=5.0, seed=3)
    layered = sample_weather(pair, load_preset("snow+alpha-white", {"1.count": 40,
                                                                    "2.count": 10}), seed=0)
    assert [r.settings.blend for r in layered.layers] == ["additive", "alpha"]
    out = render_pair(pair, layered)
    alone = [render_pair(pair, record) for record in layered.layers]
    snow = layered.layers[0]
    reach = int(build_stamps([snow], load_templates(snow.settings.templates)).side.max()) // 2 + 2
    dimmed = 0
    for frame in ("1", "2"):
        image = getattr(out, "image" + frame)[0]
        covered = [getattr(a, "opacity" + frame)[0, 0] > 0 for a in alone]
        near_white = torch.nn.functional.max_pool2d(covered[1][None].double(), 2 * reach + 1,
                                                    stride=1, padding=reach)[0] > 0
        kinds = {"snow": covered[0] & ~near_white, "white": covered[1] & ~covered[0],
                 "none": ~covered[0] & ~covered[1]}
        wants = {"snow": getattr(alone[0], "image" + frame)[0],
                 "white": getattr(alone[1], "image" + frame)[0],
                 "none": getattr(pair, "image" + frame)}
        for kind, where in kinds.items():
            assert int(where.sum()) > 0, (frame, kind)
            assert torch.equal(image[:, where], wants[kind][:, where]), (frame, kind)
        snow_only = covered[0] & ~covered[1]
        assert bool((image[:, snow_only] <= wants["snow"][:, snow_only]).all()), frame
        dimmed += int((image[:, snow_only] < wants["snow"][:, snow_only]).any(0).sum())
    assert dimmed > 0       # some flakes lie behind white particles and reach past them


def test_a_layer_absent_from_a_pixel_does_not_stop_the_others_sorting():
    """Three alpha layers at one pixel, the middle one absent there: the near red layer still
    lies over the far blue one (as with the absent layer left out)."""
    a = torch.tensor([0.5, 0.0, 0.5], dtype=torch.float64).view(1, 3, 1, 1, 1)
    c = torch.zeros(1, 3, 3, 1, 1, dtype=torch.float64)
    c[0, 0, 0], c[0, 2, 2] = 0.5, 0.5                     # layer 0 red at depth 1, 2 blue at 3
    z = a * torch.tensor([1.0, 0.0, 3.0], dtype=torch.float64).view(1, 3, 1, 1, 1)
    image = torch.zeros(1, 3, 1, 1, dtype=torch.float64)
    out, _ = composite_layers(a, c, z, image, torch.tensor([[True, True, True]]))
    assert out.flatten().tolist() == [0.5, 0.0, 0.25]     # blue under red: (0 + 0.5 b) 0.5 + r
    two, _ = composite_layers(a[:, [0, 2]], c[:, [0, 2]], z[:, [0, 2]], image,
                              torch.tensor([[True, True]]))
    assert torch.equal(out, two)


@pytest.mark.parametrize("names", ["snow-light+fog-light", "snow-light+rain-light",
                                   "fog-light+snow-light+rain-light"])
def test_a_combined_sequence_frame_is_drawn_alone_with_the_pairs_bytes(names):
    """A sequence writes each frame once: frame 1 of combined weather fields drawn from its
    view alone (additive particles dimmed by the fog in front of them, two additive layers,
    three layers through the sorting network) is frame 1 of the pair's render, bit for bit."""
    from weathergen.engine.rendering.renderer import render_first_frame

    pair = plane_pair(40, 56, depth=5.0, seed=4)
    # fog-light as wisps of haze (an alpha layer of particles) in its own atmosphere
    overrides = wisps("fog-light", 0.5, atmosphere=True) if "fog-light" in names else {}
    layered = sample_weather(pair, load_preset(names, overrides), seed=2, frame_rate=24.0)
    assert all(r.optics is not None for r in layered.layers) and min(layered.counts) > 0
    assert any(r.atmosphere is not None for r in layered.layers)
    image, opacity = render_first_frame(pair, layered)
    out = render_pair(pair, layered)
    assert torch.equal(image, out.image1) and torch.equal(opacity, out.opacity1)
    assert bool((image != pair.image1).any())


def test_particle_truth_of_combined_weather_dims_as_the_render_does(pair):
    """Particle ground truth over the layers: a flake behind a fog billboard weighs what the
    render shows of it (dimmed by the fog), so the truth's opacity is the layered render's
    opacity of frame 1; its weight is below the two layers' own weights added."""
    from weathergen.engine import particle_truth

    flake = one_particle(pair, "snow", 4.0, RED, blend="additive")
    flake = flake.replace(transparency=torch.full_like(flake.transparency, 0.5))
    cloud = one_particle(pair, "fog", 3.0, BLUE, size=41)
    cloud = cloud.replace(transparency=torch.full_like(cloud.transparency, 0.6))
    layered = LayeredParticles((flake, cloud), ("snow", "fog"))
    truth = particle_truth(pair, layered)
    out = render_pair(pair, layered)
    assert torch.allclose(truth.opacity.double(), out.opacity1[0], atol=1e-6)
    alone = [particle_truth(pair, record) for record in layered.layers]
    added = alone[0].weight + alone[1].weight
    assert bool((truth.weight <= added + 1e-9).all())
    lost = float((added - truth.weight).sum())
    assert lost > 0.2 * float(alone[0].weight.sum())         # the flake's share behind the fog
