"""Batched attacks: B pairs optimised together give the results of B single-pair runs, up to the
tolerance stated in docs/attack.md (floating-point reduction order)."""

from __future__ import annotations

import pytest
import torch

from weathergen.attack import (OPTIMIZABLE, AttackSettings, TargetSpec, attack_batch, attack_pair)
from weathergen.engine.records.particles import TENSOR_FIELDS
from weathergen.errors import ConfigError

from .test_attack_pair import crop_pair, grey_particles

#: The tolerances docs/attack.md states for batched against single-pair results: losses and
#: distances (pixels) per step; the optimised particle fields (scene units / atanh-domain values)
#: and the flows computed from them (pixels), which Adam's normalised steps make more sensitive
#: to rounding where a variable's gradient is about as small as Adam's epsilon.
RTOL, ATOL = 1e-4, 1e-4
#: Losses and distances after the first step: the network's gradient with respect to the frames
#: can differ by about 1 % at a few pixels between a batched and a single evaluation (the
#: renderer gives a pair the same bits alone or in a batch, values and gradients), and Adam then
#: moves the particles there a little differently.
STEP_RTOL = 5e-3
PARTICLE_ATOL = 1e-3
FLOW_ATOL = 5e-2


@pytest.fixture(scope="module")
def demo_pair():
    from weathergen.datasets import demo_pairs

    return demo_pairs(scenes=["courtyard"], frames_per_scene=1)[0]


@pytest.fixture(scope="module")
def raft_small(raft_small_weights):
    from weathergen.models import get_model

    return get_model("raft-small", checkpoint=raft_small_weights, iters=2)


def hidden(pair, particles):
    """The same record moved behind the first camera: nothing of it reaches the frames."""
    from weathergen.engine import reference_transforms
    from weathergen.geometry import transform_points

    _, cam1_from_ref, _ = reference_transforms(pair)
    in_camera = transform_points(cam1_from_ref, particles.position)
    in_camera[:, 2] = -50.0
    return particles.replace(position=transform_points(torch.linalg.inv(cam1_from_ref),
                                                       in_camera).float())


def assert_same_result(batched, single):
    assert batched.best_step == single.best_step
    assert batched.frozen == single.frozen
    assert [r.step for r in batched.history] == [r.step for r in single.history]
    for b, s in zip(batched.history, single.history):
        for name in ("loss", "distance", "penalty", "robustness", "best_distance"):
            assert getattr(b, name) == pytest.approx(getattr(s, name), rel=STEP_RTOL, abs=ATOL), \
                name
    for name in ("benign_flow", "initial_flow", "target"):     # before any step
        torch.testing.assert_close(getattr(batched, name), getattr(single, name),
                                   rtol=RTOL, atol=ATOL, msg=name)
    torch.testing.assert_close(batched.best_flow, single.best_flow, rtol=0, atol=FLOW_ATOL,
                               msg="best_flow")
    for name in TENSOR_FIELDS:
        a, b = getattr(batched.best_particles, name), getattr(single.best_particles, name)
        if a.is_floating_point():
            torch.testing.assert_close(a, b, rtol=0, atol=PARTICLE_ATOL, msg=name)
        else:
            assert torch.equal(a, b), name


@pytest.fixture(params=[1, pytest.param(2, marks=pytest.mark.slow)], ids=["1-thread", "2-threads"])
def threads(request):
    """Rounding differs with the number of threads torch uses: the tolerance holds for both."""
    before = torch.get_num_threads()
    torch.set_num_threads(request.param)
    yield request.param
    torch.set_num_threads(before)


def test_a_batch_equals_pairs_attacked_one_by_one(demo_pair, raft_small, threads):
    pairs = [crop_pair(demo_pair, top, left, 96, 128).validate()
             for top, left in ((40, 120), (60, 60), (0, 0))]
    records = [grey_particles(p, count=60, seed=s) for s, p in enumerate(pairs)]
    settings = AttackSettings(optimize=OPTIMIZABLE, steps=2, lr=2e-3)
    target = TargetSpec("negative")
    seen = []
    batched = attack_batch(raft_small, pairs, records, settings, target,
                           on_step=lambda i, r: seen.append((i, r.step)))
    assert sorted(seen) == [(i, s) for i in range(3) for s in range(3)]
    for pair, record, result in zip(pairs, records, batched):
        single = attack_pair(raft_small, pair, record, settings, target)
        assert result.history[-1].best_distance < result.history[0].distance   # it did optimise
        assert_same_result(result, single)


def test_nothing_visible_freezes_only_its_own_pair(demo_pair, raft_small):
    pair = crop_pair(demo_pair, 40, 120, 96, 128).validate()
    seen = grey_particles(pair, count=60)
    unseen = hidden(pair, grey_particles(pair, count=60, seed=5))
    settings = AttackSettings(optimize=("color", "transparency"), steps=2, lr=2e-3)
    batched = attack_batch(raft_small, [pair, pair], [seen, unseen], settings)
    assert not batched[0].frozen and len(batched[0].history) == 3
    assert batched[1].frozen and len(batched[1].history) == 1
    assert torch.equal(batched[1].best_particles.color, unseen.color)
    for record, result in zip((seen, unseen), batched):
        assert_same_result(result, attack_pair(raft_small, pair, record, settings))


def test_pairs_of_different_sizes_are_refused(demo_pair, raft_small):
    a = crop_pair(demo_pair, 0, 0, 64, 64).validate()
    b = crop_pair(demo_pair, 0, 0, 64, 96).validate()
    with pytest.raises(ConfigError, match="one size"):
        attack_batch(raft_small, [a, b], [grey_particles(a, 5), grey_particles(b, 5)],
                     AttackSettings(steps=1))
