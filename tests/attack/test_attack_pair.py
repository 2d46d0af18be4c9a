"""The attack's pieces and its loop: option parsing, targets, penalty, parametrisation, gradients
through RAFT-small, and the best-step bookkeeping on a small crop of the demo scene."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from weathergen.attack import (ATTACK_CONFIGS, LR_APPEARANCE, LR_POSITIONS, OPTIMIZABLE, VARIABLES,
                               AttackSettings, TargetSpec, WeatherVariables, attack_config,
                               attack_loss, attack_pair, default_lr, offset_penalty,
                               parse_optimize, parse_target, particle_depths, target_flow)
from weathergen.errors import ConfigError



def crop_pair(pair, top: int, left: int, height: int, width: int):
    """A window of a frame pair, with the principal point moved so the geometry stays exact."""
    rows, cols = slice(top, top + height), slice(left, left + width)
    k = pair.intrinsics.clone()
    k[0, 2] -= left
    k[1, 2] -= top
    crop = lambda t: None if t is None else t[:, rows, cols].contiguous()  # noqa: E731
    return dataclasses.replace(pair, image1=crop(pair.image1), image2=crop(pair.image2),
                               depth1=crop(pair.depth1), depth2=crop(pair.depth2),
                               flow=crop(pair.flow), flow_valid=crop(pair.flow_valid),
                               intrinsics=k)


@pytest.fixture(scope="module")
def small_pair():
    from weathergen.datasets import demo_pairs

    pair = demo_pairs(scenes=["courtyard"], frames_per_scene=1)[0]
    return crop_pair(pair, 40, 120, 96, 128).validate()


@pytest.fixture(scope="module")
def raft_small(raft_small_weights):
    from weathergen.models import get_model

    return get_model("raft-small", checkpoint=raft_small_weights, iters=2)


def grey_particles(pair, count=80, seed=3):
    """Mid-grey alpha-blended particles: colour and transparency sit where tanh is not flat."""
    from weathergen.engine import load_preset, sample_particles

    return sample_particles(pair, load_preset("grey", {"count": str(count)}), seed)


# -- options ------------------------------------------------------------------------------------

def test_parse_optimize_orders_and_validates():
    assert parse_optimize("color,offset1") == ("offset1", "color")
    # every variable: the particles' four, then the atmosphere's (ignored without an atmosphere)
    assert parse_optimize("all") == VARIABLES == OPTIMIZABLE + ("density", "airlight")
    with pytest.raises(ConfigError, match="offset1, offset2, color, transparency, density"):
        parse_optimize("offset1,colour")
    with pytest.raises(ConfigError):
        parse_optimize(" , ")


def test_default_learning_rates_follow_the_paper():
    assert default_lr(("offset1",)) == LR_POSITIONS == 1e-5
    assert default_lr(("color", "transparency")) == LR_APPEARANCE == 1e-3
    assert default_lr(OPTIMIZABLE) == 1e-5
    assert AttackSettings(optimize=("color",), lr=0.5).learning_rates == {"color": 0.5}


def test_settings_reject_bad_values():
    # Library messages name the parameter; the command line spells it as its option.
    with pytest.raises(ConfigError, match="^lr must be a positive number") as bad_lr:
        AttackSettings(lr=-1.0)
    assert bad_lr.value.render(lambda name: f"--{name}").startswith("--lr must")
    with pytest.raises(ConfigError, match="^steps must be >= 0"):
        AttackSettings(steps=-2)
    with pytest.raises(ConfigError, match="^alpha1 must be a finite number"):
        AttackSettings(alpha1=float("nan"))


def test_attack_configurations_match_the_supplement_table():
    # Eleven distinct rows (the Sintel-train snow row differs from snow only in its data).
    assert len(ATTACK_CONFIGS) == 11
    fog = attack_config("fog")
    assert "offset2" not in fog.optimize and fog.occlusion_gradient
    for name in ("snow", "rain", "sparks", "grey-all"):
        assert ATTACK_CONFIGS[name].optimize == OPTIMIZABLE
    for cfg in ATTACK_CONFIGS.values():
        assert cfg.lr == default_lr(cfg.optimize)
    with pytest.raises(ConfigError, match="grey-offset1"):
        attack_config("hail")


def test_parse_target_forms():
    assert parse_target("zero") == TargetSpec("zero")
    assert parse_target("negative").kind == "negative"
    assert parse_target("2.5,-1") == TargetSpec("constant", (2.5, -1.0))
    assert parse_target("goal.flo").path == Path("goal.flo")
    for bad in ("up", "1,2,3", "a,b"):
        with pytest.raises(ConfigError, match="^target "):
            parse_target(bad)


def test_target_flows():
    benign = torch.randn(1, 2, 5, 7)
    assert torch.equal(target_flow(TargetSpec("zero"), benign), torch.zeros(1, 2, 5, 7))
    assert torch.equal(target_flow(TargetSpec("negative"), benign), -benign)
    const = target_flow(TargetSpec("constant", (3.0, -2.0)), benign)
    assert torch.all(const[:, 0] == 3.0) and torch.all(const[:, 1] == -2.0)
    file_flow = torch.randn(2, 5, 7)
    assert torch.equal(target_flow(TargetSpec("file", path=Path("t.flo")), benign, file_flow)[0],
                       file_flow)
    with pytest.raises(ConfigError, match="7x5"):
        target_flow(TargetSpec("file", path=Path("t.flo")), benign, torch.zeros(2, 4, 4))


# -- loss and parametrisation --------------------------------------------------------------------

def test_offset_penalty_by_hand():
    d1 = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    d2 = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 0.0]])
    depth1, depth2 = torch.tensor([1.0, 2.0]), torch.tensor([3.0, 1.0])
    # frame 1: (1/1 + 4/2) = 3, frame 2: 9/3 = 3; weights 10 and 100; |P| = 2
    assert offset_penalty(d1, d2, depth1, depth2, 10.0, 100.0).item() == pytest.approx(165.0)
    assert offset_penalty(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0),
                          1.0, 1.0).item() == 0.0


def test_variables_start_at_the_record_and_keep_frozen_fields(small_pair):
    particles = grey_particles(small_pair)
    v = WeatherVariables(particles, OPTIMIZABLE)
    start = v.particles()
    for name in ("offset1", "offset2", "color", "transparency"):
        assert torch.allclose(getattr(start, name), getattr(particles, name), atol=1e-5)
    frozen = WeatherVariables(particles, ("color",))
    with torch.no_grad():
        frozen.delta["color"].add_(50.0)          # far into the flat part of tanh
    moved = frozen.particles()
    assert torch.equal(moved.transparency, particles.transparency)
    assert torch.equal(moved.offset1, particles.offset1)
    assert bool(((moved.color > 0) & (moved.color < 1)).all())  # the box trick keeps (0, 1)


def test_transparency_above_one_survives_the_box_transform():
    from weathergen.engine import empty_particles

    base = empty_particles("camera1")
    theta = torch.tensor([0.2, 1.4])
    record = base.replace(position=torch.zeros(2, 3), motion=torch.zeros(2, 3),
                          offset1=torch.zeros(2, 3), offset2=torch.zeros(2, 3),
                          color=torch.full((2, 3), 0.5), transparency=theta,
                          template=torch.zeros(2, dtype=torch.long), rotation=torch.zeros(2),
                          scale=torch.ones(2), defocus=torch.zeros(2, dtype=torch.long))
    v = WeatherVariables(record, ("transparency",))
    assert torch.allclose(v.particles().transparency, theta, atol=1e-5)


def test_particle_depths_are_camera_z(small_pair):
    from weathergen.engine.sampling.pair import reference_transforms
    from weathergen.geometry import transform_points

    particles = grey_particles(small_pair, count=20)
    _, c1, c2 = reference_transforms(small_pair)
    d1, d2 = particle_depths(particles, c1, c2)
    z1 = transform_points(c1, particles.position.double())[:, 2].clamp(min=1e-3)
    assert torch.allclose(d1.double(), z1, rtol=1e-5)
    assert d2.shape == (20,) and bool((d2 > 0).all())


# -- through the network ------------------------------------------------------------------------

def test_gradient_reaches_every_variable_through_raft(small_pair, raft_small):
    from weathergen.engine import render
    from weathergen.engine.sampling.pair import reference_transforms

    particles = grey_particles(small_pair)
    _, c1, c2 = reference_transforms(small_pair)
    v = WeatherVariables(particles, OPTIMIZABLE)
    current = v.particles()
    out = render(small_pair.image1[None], small_pair.image2[None], small_pair.depth1[None],
                 small_pair.depth2[None], small_pair.intrinsics[None], c1[None], c2[None],
                 current)
    flow = raft_small(out.image1, out.image2)
    d1, d2 = particle_depths(particles, c1, c2)
    loss, distance, penalty = attack_loss(flow, torch.zeros_like(flow), current, d1, d2)
    assert penalty.item() == 0.0                 # offsets start at zero: the flow term alone
    loss.backward()
    for name, delta in v.delta.items():
        assert delta.grad is not None, name
        assert bool(torch.isfinite(delta.grad).all()), name
        assert delta.grad.abs().sum().item() > 0, f"no gradient reaches {name}"


def test_loop_keeps_the_best_step_and_improves(small_pair, raft_small):
    particles = grey_particles(small_pair)
    settings = AttackSettings(optimize=OPTIMIZABLE, steps=3, lr=2e-3)
    seen = []
    result = attack_pair(raft_small, small_pair, particles, settings, TargetSpec("zero"),
                         on_step=seen.append)
    steps = [r.step for r in result.history]
    assert steps == [0, 1, 2, 3] and seen == result.history
    best = [r.best_distance for r in result.history]
    assert all(b <= a for a, b in zip(best, best[1:])), best
    assert best[-1] < result.history[0].distance
    assert best[-1] == min(r.distance for r in result.history)
    assert result.history[result.best_step].distance == best[-1]
    # Step 0 is the unoptimised weather: its flow is the initial flow.
    assert result.history[0].penalty == 0.0
    assert result.best_flow.shape == result.initial_flow.shape == (1, 2, 96, 128)
    # The best record reproduces the best step's flow.
    from weathergen.engine import render_pair

    with torch.no_grad():
        out = render_pair(small_pair, result.best_particles)
        again = raft_small(out.image1, out.image2)
    assert torch.allclose(again, result.best_flow, atol=1e-3)


def test_pair_optimisation_takes_the_loops_steps(small_pair, raft_small):
    """The single-pair state (the benchmark's step): one record in, 0-d terms out, the same
    losses as the loop's records."""
    from weathergen.attack import PairOptimisation

    particles = grey_particles(small_pair)
    settings = AttackSettings(optimize=OPTIMIZABLE, steps=2, lr=2e-3)
    result = attack_pair(raft_small, small_pair, particles, settings)
    run = PairOptimisation(raft_small, small_pair, particles, settings)
    for record in result.history:
        current, flow, loss, distance, penalty = run.evaluate()
        assert loss.dim() == distance.dim() == penalty.dim() == 0
        assert flow.shape == (1, 2, 96, 128) and current.count == particles.count
        assert loss.item() == pytest.approx(record.loss, rel=1e-5, abs=1e-6)
        run.update(loss)
    out = run.render(run.variables.particles())
    assert out.image1.shape == out.image2.shape == (1, 3, 96, 128)


def test_zero_steps_measure_only_the_random_weather(small_pair, raft_small):
    particles = grey_particles(small_pair, count=30)
    result = attack_pair(raft_small, small_pair, particles, AttackSettings(steps=0))
    assert len(result.history) == 1 and result.best_step == 0
    assert torch.equal(result.best_flow, result.initial_flow)
    assert torch.equal(result.best_particles.offset1, particles.offset1)


def test_particles_from_another_frame_are_refused(small_pair, raft_small):
    particles = grey_particles(small_pair, count=5).replace(frame="camera1")
    with pytest.raises(ConfigError, match="coordinates"):
        attack_pair(raft_small, small_pair, particles, AttackSettings(steps=1))


def test_attack_runs_on_pairs_sampled_from_a_weather_field(small_pair, raft_small):
    """Field records (per-frame looks) go through the same loop: offsets and loss unchanged."""
    from weathergen.engine import load_preset, render_pair, sample_weather

    particles = sample_weather(small_pair, load_preset("snow-moderate", {"far": "6"}), 4,
                               frame_rate=24.0)      # the demo scene's rate
    assert particles.optics is not None and particles.count > 100
    settings = AttackSettings(optimize=OPTIMIZABLE, steps=2, lr=2e-3)
    result = attack_pair(raft_small, small_pair, particles, settings, TargetSpec("zero"))
    assert [r.step for r in result.history] == [0, 1, 2]
    assert result.best_particles.optics == particles.optics
    moved = (result.best_particles.offset1 - particles.offset1).abs().sum()
    assert result.best_step == 0 or float(moved) > 0
    with torch.no_grad():
        out = render_pair(small_pair, result.best_particles)
        again = raft_small(out.image1, out.image2)
    assert torch.allclose(again, result.best_flow, atol=1e-3)


# -- the paper's bounds and axes ------------------------------------------------------------------

def _record(theta, position=None):
    from weathergen.engine import empty_particles

    n = len(theta)
    return empty_particles("camera1").replace(
        position=torch.zeros(n, 3) if position is None else position, motion=torch.zeros(n, 3),
        offset1=torch.zeros(n, 3), offset2=torch.zeros(n, 3), color=torch.full((n, 3), 0.5),
        transparency=torch.tensor(theta), template=torch.zeros(n, dtype=torch.long),
        rotation=torch.zeros(n), scale=torch.ones(n), defocus=torch.zeros(n, dtype=torch.long))


def test_transparency_bound_is_the_presets_not_the_samples():
    """θ ≤ max(1, the preset's θ): sparks (θ 1.5) may reach 1.5 even where its sampled particles
    stop at 1.1; snow (0.75) stays below 1 as in the paper's atanh box."""
    from weathergen.attack import plan_attack

    sparks = plan_attack(None, "sparks").settings
    assert sparks.transparency_max == 1.5
    assert plan_attack(None, "snow").settings.transparency_max == 1.0
    assert plan_attack("grey-all").settings.transparency_max == 1.0
    v = WeatherVariables(_record([0.2, 1.1]), ("transparency",),
                         transparency_max=sparks.transparency_max)
    assert v.theta_max == 1.5
    assert torch.allclose(v.particles().transparency, torch.tensor([0.2, 1.1]), atol=1e-5)
    with torch.no_grad():
        v.delta["transparency"].fill_(20.0)         # saturate: θ goes to the bound
    assert torch.allclose(v.particles().transparency, torch.full((2,), 1.5), atol=1e-4)
    # A record above the bound keeps its own largest θ as the bound (its start stays exact).
    above = WeatherVariables(_record([0.2, 1.8]), ("transparency",), transparency_max=1.5)
    assert above.theta_max == pytest.approx(1.8)


def test_offsets_move_along_the_cameras_axes():
    """Δ1 = (1, 0, 0) moves the particle one unit along camera 1's x axis, Δ2 = (0, 0, 1) one
    unit along camera 2's z axis (the paper's equations), whatever the reference frame."""
    import math

    from weathergen.geometry import transform_points

    def pose(angle, axis, t):
        c, s = math.cos(angle), math.sin(angle)
        r = {"z": [[c, -s, 0], [s, c, 0], [0, 0, 1]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]]}[axis]
        m = torch.eye(4, dtype=torch.float64)
        m[:3, :3] = torch.tensor(r, dtype=torch.float64)
        m[:3, 3] = torch.tensor(t, dtype=torch.float64)
        return m

    c1, c2 = pose(0.7, "z", [0.1, -0.2, 0.3]), pose(-0.4, "y", [1.0, 0.5, -0.2])
    record = _record([0.5, 0.5], position=torch.tensor([[0.3, 0.1, 2.0], [-0.5, 0.2, 4.0]]))
    v = WeatherVariables(record, ("offset1", "offset2"), cam1_from_ref=c1, cam2_from_ref=c2)
    with torch.no_grad():
        v.delta["offset1"][:, 0] = 1.0
        v.delta["offset2"][:, 2] = 1.0
    moved = v.particles()
    p, m = record.position.double(), record.motion.double()
    x1_before = transform_points(c1, p)
    x1_after = transform_points(c1, p + moved.offset1.double())
    assert torch.allclose(x1_after - x1_before, torch.tensor([[1.0, 0, 0]] * 2, dtype=torch.float64),
                          atol=1e-6)
    x2_before = transform_points(c2, p + moved.offset1.double() + m)
    x2_after = transform_points(c2, p + moved.offset1.double() + m + moved.offset2.double())
    assert torch.allclose(x2_after - x2_before, torch.tensor([[0, 0, 1.0]] * 2, dtype=torch.float64),
                          atol=1e-6)
