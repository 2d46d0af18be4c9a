"""The attack optimises the atmosphere itself: the density of the fog (within its bounds) and,
when asked, the airlight, through RAFT-small, on the CPU and on CUDA."""

from __future__ import annotations

import pytest
import torch

from weathergen.attack import (ATMOSPHERE_VARIABLES, DENSITY_FACTOR, FIELD_LR, OPTIMIZABLE,
                               VARIABLES, AttackSettings,
                               TargetSpec, WeatherVariables, attack_pair, parse_optimize,
                               plan_attack)
from weathergen.engine import load_preset, render_pair, sample_weather
from weathergen.errors import ConfigError

from .test_attack_pair import crop_pair

RATE = 24.0      # the demo scene's frame rate


@pytest.fixture(scope="module")
def small_pair():
    from weathergen.datasets import demo_pairs

    pair = demo_pairs(scenes=["street"], frames_per_scene=1)[0]
    return crop_pair(pair, 40, 120, 96, 128).validate()


@pytest.fixture(scope="module")
def raft_small(raft_small_weights):
    from weathergen.models import get_model

    return get_model("raft-small", checkpoint=raft_small_weights, iters=2)


def fog(pair, name="fog-heavy", seed=0):
    return sample_weather(pair, load_preset(name), seed, frame_rate=RATE)


def test_the_atmospheres_variables_are_named_and_freed_by_default_for_fog():
    assert parse_optimize("density,color") == ("color", "density")
    assert parse_optimize("all") == VARIABLES == OPTIMIZABLE + ATMOSPHERE_VARIABLES
    with pytest.raises(ConfigError, match="density, airlight"):
        parse_optimize("fog")
    assert plan_attack(preset="fog-moderate").settings.optimize == VARIABLES
    assert plan_attack(preset="snow+fog-light").settings.optimize == VARIABLES
    assert plan_attack(preset="snow").settings.optimize == OPTIMIZABLE
    assert plan_attack(preset="sparks-light").settings.optimize == OPTIMIZABLE
    assert plan_attack(preset="fog-moderate", optimize="density,airlight").settings.optimize \
        == ATMOSPHERE_VARIABLES


def test_variables_start_at_the_record_and_stay_within_their_bounds(small_pair):
    record = fog(small_pair)
    v = WeatherVariables(record, ("density", "airlight"))
    start = v.particles()
    lattice = record.atmosphere.lattice(torch.float32)
    assert torch.allclose(start.atmosphere.density, lattice, atol=1e-5)
    assert torch.allclose(start.atmosphere.airlight.double(), record.atmosphere.airlight,
                          atol=1e-5)
    with torch.no_grad():
        for p in v.atmosphere_parameters():
            p.add_(torch.randn_like(p) * 50)                 # anywhere in the tanh domain
    with torch.no_grad():
        moved = v.particles().atmosphere
    ratio = moved.density / lattice          # within DENSITY_FACTOR of the sampled value
    assert float(ratio.min()) >= 1 / DENSITY_FACTOR * (1 - 1e-6)
    assert float(ratio.max()) <= DENSITY_FACTOR * (1 + 1e-6)
    assert float((ratio - 1).abs().max()) > 1                # and far from it
    assert float(moved.airlight.min()) > 0 and float(moved.airlight.max()) < 1
    assert v.parameters() == [] or all(p.numel() == 0 for p in v.parameters())   # no particles


def test_an_attack_on_fog_lowers_its_loss_and_the_best_record_reproduces_it(small_pair,
                                                                          raft_small):
    record = fog(small_pair)
    assert record.count == 0
    settings = AttackSettings(optimize=("density", "airlight"), steps=2)
    assert settings.learning_rates == {"density": FIELD_LR["density"],
                                       "airlight": FIELD_LR["airlight"]}
    result = attack_pair(raft_small, small_pair, record, settings, TargetSpec("zero"))
    losses = [r.loss for r in result.history]
    assert not result.frozen
    assert min(losses[1:]) < losses[0], losses                # a step lowers the loss
    best = result.best_particles.atmosphere
    assert best.density is not None and not torch.equal(
        best.density, record.atmosphere.lattice(torch.float32))
    with torch.no_grad():
        out = render_pair(small_pair, result.best_particles)
        again = raft_small(out.image1, out.image2)
    assert torch.allclose(again, result.best_flow, atol=1e-3)


def test_combined_weather_frees_its_fog_layers_density(small_pair, raft_small):
    layers = sample_weather(small_pair, load_preset("rain-moderate+fog-heavy",
                                                    {"rain-moderate.density": "20"}),
                            1, frame_rate=RATE)
    settings = AttackSettings(optimize=("color", "density"), steps=1, lr=1e-2,
                              layers=("fog-heavy",))
    result = attack_pair(raft_small, small_pair, layers, settings, TargetSpec("zero"))
    rain, fog_layer = result.best_particles.layers
    assert rain.atmosphere.density is None                     # not freed
    if result.best_step > 0:
        assert fog_layer.atmosphere.density is not None


@pytest.mark.cuda
def test_an_attack_on_fog_runs_on_cuda_as_on_the_cpu(small_pair, raft_small_weights):
    from weathergen.models import get_model

    record = fog(small_pair)
    settings = AttackSettings(optimize=("density", "airlight"), steps=2)
    results = []
    for device in ("cpu", "cuda"):
        model = get_model("raft-small", checkpoint=raft_small_weights, iters=2, device=device)
        results.append(attack_pair(model, small_pair, record, settings, TargetSpec("zero"),
                                   device=device))
    cpu, gpu = results
    assert min(r.loss for r in gpu.history[1:]) < gpu.history[0].loss
    assert abs(gpu.history[0].distance - cpu.history[0].distance) < 0.05


def test_moderate_fog_doubles_its_effect_within_five_steps(raft_small_weights):
    """docs/attack.md, "Learning rates": on the demo street's first pair, RAFT-small (shipped
    checkpoint, 12 iterations) on the CPU, fog-moderate with the default variables and rates
    more than doubles AEE(f, f̌) of the random fog within 5 steps."""
    from weathergen.datasets import open_dataset
    from weathergen.jobs import pair_particles
    from weathergen.models import get_model

    dataset = open_dataset("demo", scenes=["street"], frames_per_scene=1)
    pair = dataset.load(dataset.pairs()[0])
    plan = plan_attack(preset="fog-moderate", steps=5)
    record = pair_particles(pair, plan.preset, 0, world_up=dataset.world_up,
                            frame_rate=dataset.frame_rate)
    model = get_model("raft-small", checkpoint=raft_small_weights)
    result = attack_pair(model, pair, record, plan.settings)
    best = result.history[result.best_step]
    assert best.robustness > 2 * result.history[0].robustness, [
        (r.step, r.robustness) for r in result.history]
