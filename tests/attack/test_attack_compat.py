"""``compat="reference"``: each term in which the research code departs from the paper, one test
per term, each showing the reference mode's behaviour and the paper mode's (the default)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from weathergen.attack import (AttackSettings, PairOptimisation, PairSummary, WeatherVariables,
                               offset_penalty, plan_attack, summarize_pair)
from weathergen.attack.compat import (REFERENCE_DEPTH_EPS, detaches_occlusion,
                                      reference_offset_penalty, resets_gradients)
from weathergen.attack.pair import AttackResult, start_depth
from weathergen.engine import BETA_ATTACK, BETA_RENDER
from weathergen.engine.rendering.renderer import depth_seen
from weathergen.engine.weather.templates import load_templates
from weathergen.errors import ConfigError
from weathergen.geometry import transform_points

from .test_attack_pair import crop_pair, grey_particles


@pytest.fixture(scope="module")
def small_pair():
    from weathergen.datasets import demo_pairs

    pair = demo_pairs(scenes=["courtyard"], frames_per_scene=1)[0]
    return crop_pair(pair, 40, 120, 96, 128).validate()


@pytest.fixture(scope="module")
def raft_small(raft_small_weights):
    from weathergen.models import get_model

    return get_model("raft-small", checkpoint=raft_small_weights, iters=2)


def on_the_surface(pair, particles, gap=0.003):
    """The particles moved along their frame-1 camera rays to just in front of the scene
    surface they cover (V about 0.7 at β = 250): occlusion's gradient is large there."""
    from weathergen.engine.sampling.pair import reference_transforms
    from weathergen.geometry import project

    _, c1, _ = reference_transforms(pair)
    x1 = transform_points(c1, particles.position.double())
    pix, z = project(x1, pair.intrinsics.double())
    h, w = pair.depth1.shape[-2:]
    u = pix[:, 0].round().long().clamp(0, w - 1)
    v = pix[:, 1].round().long().clamp(0, h - 1)
    surface = pair.depth1[0, v, u].double()
    x1 = x1 * ((surface - gap) / z)[:, None]
    back = transform_points(torch.linalg.inv(c1), x1)
    return particles.replace(position=back.float())


def settings(compat, **kw):
    return AttackSettings(compat=compat, lr=2e-3, **kw)


def test_compat_is_validated_and_recorded():
    assert AttackSettings().compat == "paper"
    assert AttackSettings(compat="reference").to_dict()["compat"] == "reference"
    with pytest.raises(ConfigError, match="^compat must be one of paper, reference"):
        AttackSettings(compat="authors")


# -- gradient reset --------------------------------------------------------------------------------

@pytest.mark.parametrize("compat", ["paper", "reference"])
def test_gradients_reset_per_step_or_accumulate(small_pair, raft_small, compat):
    """Paper: each Adam step sees its own gradient; reference: the sum of every step's so far."""
    particles = grey_particles(small_pair, count=60)
    run = PairOptimisation(raft_small, small_pair, particles,
                           settings(compat, optimize=("color", "transparency")))
    assert resets_gradients(run.settings) == (compat == "paper")
    params = run.variables.parameters()
    total = [torch.zeros_like(p) for p in params]
    for _ in range(3):
        _, _, loss, _, _ = run.evaluate()
        own = torch.autograd.grad(loss, params, retain_graph=True)
        total = [t + g for t, g in zip(total, own)]
        run.update(loss)
        expected = own if compat == "paper" else total
        for p, e in zip(params, expected):
            assert torch.allclose(p.grad, e, rtol=1e-5, atol=1e-9)
    # After three steps the two differ: the accumulated sum is not the last gradient.
    assert not torch.allclose(total[0], own[0], rtol=1e-3)


# -- occlusion -----------------------------------------------------------------------------------

def test_reference_detaches_occlusion_unless_it_is_softened(small_pair, raft_small):
    """The research code detaches V at β = 250 and differentiates it at β = 30 (fog); the paper's
    V is always differentiable. Same forward pass, same colour gradient; the offsets' gradient
    loses V's share."""
    assert not detaches_occlusion(AttackSettings(compat="paper"))
    assert detaches_occlusion(AttackSettings(compat="reference", beta=BETA_RENDER))
    assert not detaches_occlusion(AttackSettings(compat="reference", beta=BETA_ATTACK))
    assert plan_attack(None, "fog", compat="reference").settings.beta == BETA_ATTACK

    particles = on_the_surface(small_pair, grey_particles(small_pair, count=80))
    # footprints n + 1/4 pixels (n >= 2) and no defocus: stamps the research code's way
    # (``stamp_style = "research"``, the reference mode's) are then weathergen's own
    res = load_templates(particles.settings.templates).resolution
    footprint = (particles.scale.double() * res).round().clamp(min=2) + 0.25
    particles = particles.replace(scale=(footprint / res).to(particles.scale.dtype),
                                  defocus=torch.zeros_like(particles.defocus))
    # the reference mode reads the depth half a pixel up and left: the paper mode gets the depth
    # read there, so that both test the particles against the same depth
    shifted = dataclasses.replace(small_pair, **{k: depth_seen(getattr(small_pair, k)[None],
                                                               [0.5])[0]
                                                 for k in ("depth1", "depth2")})
    grads, distances = {}, {}
    for compat, pair in (("paper", shifted), ("reference", small_pair)):
        # offset2 and colour only: no homogeneous component, no transparency bound, and both
        # penalties have zero gradient at the start.
        run = PairOptimisation(raft_small, pair, particles,
                               settings(compat, optimize=("offset2", "color")))
        assert run.detach_occlusion == (compat == "reference")
        _, _, loss, distance, _ = run.evaluate()
        loss.backward()
        grads[compat] = {k: v.grad.clone() for k, v in run.variables.delta.items()}
        distances[compat] = distance.item()
    assert distances["paper"] == distances["reference"]
    assert torch.allclose(grads["paper"]["color"], grads["reference"]["color"], rtol=1e-5,
                          atol=1e-10)
    assert not torch.allclose(grads["paper"]["offset2"], grads["reference"]["offset2"],
                              rtol=1e-4, atol=0)


# -- offset penalty ------------------------------------------------------------------------------

def test_reference_penalty_by_hand():
    d1 = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    d2 = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 0.0]])
    z1 = torch.tensor([1.0, 2.0])
    # frame 1: (1/1 + 4/4) / 2 = 1, frame 2: (9/1 + 0) / 2 = 4.5 (both over frame 1's depth²)
    expected = 10.0 * 1.0 + 100.0 * 4.5
    got = reference_offset_penalty(d1, d2, z1, 10.0, 100.0).item()
    assert got == pytest.approx(expected, rel=1e-6)
    assert REFERENCE_DEPTH_EPS == 1e-7
    assert reference_offset_penalty(None, d2, z1, 10.0, 100.0).item() == pytest.approx(450.0, rel=1e-6)


@pytest.mark.parametrize("compat", ["paper", "reference"])
def test_penalty_of_each_mode(small_pair, raft_small, compat):
    """The loop's penalty: the paper's ‖δ_t‖²/d_t with each frame's depth, or the research
    code's ‖Δ_t‖²/(z1² + ε) with the squared frame-1 depth for both."""
    from weathergen.engine.sampling.pair import reference_transforms

    particles = grey_particles(small_pair, count=40)
    run = PairOptimisation(raft_small, small_pair, particles,
                           settings(compat, optimize=("offset1", "offset2"), alpha1=3.0, alpha2=5.0))
    with torch.no_grad():
        run.variables.delta["offset1"].normal_(0, 0.01)
        run.variables.delta["offset2"].normal_(0, 0.02)
    current, _, _, _, penalty = run.evaluate()
    _, c1, c2 = reference_transforms(small_pair)
    d = run.variables.delta
    if compat == "paper":
        d1, d2 = run.reg_depths[0]
        expected = offset_penalty(current.offset1, current.offset2, d1, d2, 3.0, 5.0)
        assert not torch.allclose(d1, d2)
    else:
        z1 = transform_points(c1, particles.position.double())[:, 2]
        assert torch.allclose(start_depth(particles, c1).double(), z1, rtol=1e-6)
        scale = z1.pow(2) + REFERENCE_DEPTH_EPS
        expected = (3.0 * (d["offset1"].double().pow(2).sum(1) / scale).mean()
                    + 5.0 * (d["offset2"].double().pow(2).sum(1) / scale).mean())
    assert penalty.item() == pytest.approx(float(expected.detach()), rel=1e-5)
    other = reference_offset_penalty(d["offset1"], d["offset2"], run.start_depth1[0], 3.0, 5.0) \
        if compat == "paper" else offset_penalty(current.offset1, current.offset2,
                                                   *run.reg_depths[0], 3.0, 5.0)
    assert penalty.item() != pytest.approx(other.item(), rel=1e-3)


# -- homogeneous offsets -------------------------------------------------------------------------

def test_reference_homogeneous_component_moves_frame_two_along_the_camera_translation(small_pair):
    from weathergen.engine.sampling.pair import reference_transforms

    _, c1, c2 = reference_transforms(small_pair)
    particles = grey_particles(small_pair, count=10)
    paper = WeatherVariables(particles, ("offset1", "color"), cam1_from_ref=c1, cam2_from_ref=c2)
    assert "offset1_w" not in paper.delta
    # Only with offset1 freed (the research code learns it as part of δ1).
    assert "offset1_w" not in WeatherVariables(particles, ("offset2",), cam1_from_ref=c1,
                                               cam2_from_ref=c2, homogeneous=True).delta
    ref = WeatherVariables(particles, ("offset1", "color"), cam1_from_ref=c1, cam2_from_ref=c2,
                           homogeneous=True)
    assert ref.delta["offset1_w"].shape == (10,)
    with torch.no_grad():
        ref.delta["offset1_w"].fill_(0.5)
    moved = ref.particles()
    p, m = particles.position.double(), particles.motion.double()
    x1 = transform_points(c1, p + moved.offset1.double())
    x1_start = transform_points(c1, p + particles.offset1.double())
    assert torch.allclose(x1, x1_start, atol=1e-6)                       # frame 1 unchanged
    x2 = transform_points(c2, p + moved.offset1.double() + m + moved.offset2.double())
    x2_start = transform_points(c2, p + particles.offset1.double() + m + particles.offset2.double())
    t = (c2 @ torch.linalg.inv(c1))[:3, 3]
    assert float(t.norm()) > 0.01
    assert torch.allclose(x2 - x2_start, 0.5 * t.expand(10, 3), atol=1e-5)


def test_the_loop_frees_the_homogeneous_component_only_in_reference_mode(small_pair, raft_small):
    particles = grey_particles(small_pair, count=10)
    for compat, has in (("paper", False), ("reference", True)):
        run = PairOptimisation(raft_small, small_pair, particles, settings(compat))
        assert ("offset1_w" in run.variables.delta) == has
        groups = {g["group"]: g["params"] for g in run.optimizer.param_groups}
        assert sum(len(p) for p in groups.values()) == 4 + has
        assert len(groups["positions"]) == 2 + has      # (offset1_w moves with the positions)


# -- blending of motion blur ---------------------------------------------------------------------

def test_reference_blends_alpha_motion_blur_sample_by_sample(small_pair, raft_small):
    """The research code blends an α-blended particle's blur samples one after another; the
    attack draws (and differentiates) the same frames as ``render_pair`` of the record so
    marked."""
    from weathergen.engine import load_preset, render_pair, sample_particles

    particles = sample_particles(small_pair, load_preset("alpha-white", {"count": "60"}), 3)
    frames = {}
    for compat, order in (("paper", "sum"), ("reference", "sequential")):
        run = PairOptimisation(raft_small, small_pair, particles, settings(compat))
        current = run.variables.particles()
        assert current.settings.blur_blend == order
        out = run.render(current)
        with torch.no_grad():
            want = render_pair(small_pair, particles.for_compat(compat), beta=run.settings.beta)
        assert torch.allclose(out.image1, want.image1, atol=1e-6)
        out.image1.sum().backward()
        grads = [p.grad for p in run.variables.parameters()]
        assert any(g is not None and float(g.abs().sum()) > 0 for g in grads)
        frames[compat] = out.image1.detach()
    assert float((frames["paper"] - frames["reference"]).abs().max()) > 1e-3


# -- transparency bound --------------------------------------------------------------------------

def test_reference_caps_transparency_at_the_presets():
    for name, paper, reference in (("snow", 1.0, 0.75), ("rain", 1.0, 0.75), ("sparks", 1.5, 1.5),
                                   ("grey", 1.0, 0.75), ("fog", 1.0, 0.25)):
        assert plan_attack(None, name).settings.transparency_max == paper, name
        got = plan_attack(None, name, compat="reference").settings
        assert got.transparency_max == reference and got.compat == "reference", name
    # a constant-transparency preset (the caption's fog) has no counterpart in the research code
    constant = plan_attack(None, "fog", overrides={"transparency_mode": "constant",
                                                   "transparency": 0.3}, compat="reference")
    assert constant.settings.transparency_max == 1.0


# -- figures -------------------------------------------------------------------------------------

def _result(best_step):
    """Hand-made flows: benign 0, random weather 3 px right, best 3 px right and 4 px down."""
    shape = (1, 2, 4, 5)
    benign = torch.zeros(shape)
    initial = torch.zeros(shape)
    initial[:, 0] = 3.0
    best = initial.clone()
    best[:, 1] = 4.0
    return AttackResult(best_particles=None, best_step=best_step, history=[None] * 4,
                        benign_flow=benign, initial_flow=initial,
                        best_flow=best if best_step else initial, target=torch.zeros(shape))


def test_figures_of_each_mode():
    written = torch.zeros(1, 2, 4, 5)
    written[:, 1] = 4.5                                  # the 8-bit frames' flow differs a little
    paper = summarize_pair("p", _result(2), written)
    assert paper.aee_adversarial == pytest.approx(4.5)                   # AEE(f, f̌ written)
    assert paper.target_adversarial == pytest.approx(4.5)
    ref = summarize_pair("p", _result(2), written, compat="reference")
    assert ref.aee_adversarial == pytest.approx(4.0)     # AEE(f̌ best, f̌ random): |(0, 4)|
    assert ref.target_adversarial == pytest.approx(5.0)  # float best frames: |(3, 4)|
    assert ref.aee_random == paper.aee_random == pytest.approx(3.0)
    # No step beat step 0: the random weather against the clean flow.
    still = summarize_pair("p", _result(0), written, compat="reference")
    assert still.aee_adversarial == pytest.approx(3.0)
    assert isinstance(still, PairSummary) and math.isfinite(still.target_adversarial)
