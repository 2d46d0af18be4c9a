"""Early stopping (``--early-stop WINDOW:TOL``): the rule on a loss history, its settings and
record, and the attack loop ending a pair whose loss is flat, not one whose loss falls, with the
best iterate kept."""

from __future__ import annotations

import pytest

from weathergen.attack import AttackSettings, EarlyStop, attack_batch
from weathergen.errors import ConfigError
from weathergen.models.base import FlowModel


def test_a_flat_loss_has_converged_a_falling_one_has_not():
    stop = EarlyStop(3, 0.01)
    assert not stop.stalled([5.0, 5.0, 5.0])                  # not yet a window after step 0
    assert stop.stalled([5.0, 5.0, 5.0, 5.0])                 # flat over 3 steps
    assert not stop.stalled([5.0, 4.0, 3.0, 2.0])             # falling
    # the window's best must beat the earlier best by more than 1 % of it
    assert stop.stalled([5.0, 4.96, 4.97, 4.99])              # 0.8 % better: converged
    assert not stop.stalled([5.0, 5.1, 5.2, 4.9])             # 2 % better in the window
    assert stop.stalled([4.0, 3.0, 3.5, 3.2, 3.1])            # best (3.0) before the window
    assert EarlyStop(1, 0.0).stalled([1.0, 1.0]) and not EarlyStop(1, 0.0).stalled([1.0, 0.99])


def test_parsing_and_validation():
    assert EarlyStop.parse("50:0.001") == EarlyStop(50, 0.001)
    assert str(EarlyStop(50, 0.001)) == "50:0.001"
    for bad in ("50", "x:1", "50:y", "0:0.1", "5:-1", "5:nan", "1.5:0.1"):
        with pytest.raises(ConfigError, match="^early_stop"):
            EarlyStop.parse(bad)


def test_recorded_in_the_settings_and_refused_under_compat_reference():
    settings = AttackSettings(steps=10, early_stop=EarlyStop(4, 0.01))
    assert settings.to_dict()["early_stop"] == "4:0.01"
    assert "early_stop" not in AttackSettings(steps=10).to_dict()     # the paper's: every step
    with pytest.raises(ConfigError, match="^early_stop does not apply under compat reference"):
        AttackSettings(compat="reference", early_stop=EarlyStop(4, 0.01))


class Brightness(FlowModel):
    """Flow ``scale`` times the frames' mean brightness, the same at every pixel (``scale`` 0:
    a constant flow whatever the weather, so the loss is flat)."""

    def __init__(self, scale: float):
        super().__init__()
        self.scale = scale

    def normalize(self, image):
        return image

    def predict(self, image1, image2):
        level = (image1 + image2).mean(dim=(1, 2, 3), keepdim=True)
        return (1.0 + self.scale * level).expand(-1, 2, *image1.shape[-2:])


@pytest.fixture(scope="module")
def pair_and_particles():
    from weathergen.datasets import demo_pairs
    from weathergen.engine import load_preset, sample_particles
    from weathergen.training.augment import crop_pair

    pair = crop_pair(demo_pairs(scenes=["courtyard"], frames_per_scene=1)[0], 40, 120, 48, 64)
    return pair, sample_particles(pair, load_preset("grey", {"count": "60"}), 3)


def run(scale, early_stop, pair_and_particles, steps=12):
    pair, particles = pair_and_particles
    settings = AttackSettings(optimize=("color", "transparency"), steps=steps,
                              early_stop=early_stop)
    return attack_batch(Brightness(scale), [pair], [particles], settings)[0]


def test_the_attack_ends_a_pair_whose_loss_is_flat(pair_and_particles):
    result = run(0.0, EarlyStop(3, 0.0), pair_and_particles)
    assert [r.step for r in result.history] == [0, 1, 2, 3]      # a window after step 0
    assert not result.frozen and result.best_step == 0
    full = run(0.0, None, pair_and_particles)
    assert len(full.history) == 13                               # every step without it


def test_the_attack_goes_on_while_the_loss_falls_and_keeps_the_best_step(pair_and_particles):
    # The frames' brightness moves the flow away from the zero target: the attack darkens the
    # particles and the loss falls at every step.
    result = run(2.0, EarlyStop(3, 0.0), pair_and_particles)
    losses = [r.loss for r in result.history]
    assert len(losses) == 13 and all(b < a for a, b in zip(losses, losses[1:]))
    distances = [r.distance for r in result.history]
    assert result.best_step == distances.index(min(distances)) == 12
    # a tolerance the falling loss does not beat: it stops, the best step among those run kept
    stopped = run(2.0, EarlyStop(2, 0.5), pair_and_particles)
    assert len(stopped.history) == 3
    assert [r.distance for r in stopped.history] == distances[:3]     # the same steps
    assert stopped.best_step == 2 and stopped.best_particles is not None
