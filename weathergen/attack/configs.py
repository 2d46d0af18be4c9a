"""Attack configurations: named settings of the paper's supplement (preset, freed variables,
learning rate, gradient through occlusion)."""

from __future__ import annotations

from dataclasses import dataclass

from ..errors import ConfigError
from .settings import LR_APPEARANCE, LR_POSITIONS, OPTIMIZABLE

@dataclass(frozen=True)
class AttackConfig:
    """One row of the supplement's "Attack configurations" table (all: Adam, 750 steps,
    α1 = α2 = 1000, Sintel-tr115 = ``--frames-per-scene 5``)."""

    name: str
    preset: str
    optimize: tuple[str, ...]
    lr: float
    occlusion_gradient: bool = False
    description: str = ""


def _configs(*rows: AttackConfig) -> dict[str, AttackConfig]:
    return {r.name: r for r in rows}


ATTACK_CONFIGS: dict[str, AttackConfig] = _configs(
    AttackConfig("grey-offset1", "grey", ("offset1",), LR_POSITIONS,
                 description="grey particles, offset before the motion only"),
    AttackConfig("grey-offset2", "grey", ("offset2",), LR_POSITIONS,
                 description="grey particles, offset after the motion only"),
    AttackConfig("grey-color", "grey", ("color",), LR_APPEARANCE,
                 description="grey particles, colour only"),
    AttackConfig("grey-transparency", "grey", ("transparency",), LR_APPEARANCE,
                 description="grey particles, transparency only"),
    AttackConfig("grey-offsets", "grey", ("offset1", "offset2"), LR_POSITIONS,
                 description="grey particles, both offsets (the paper's δ_{1,2})"),
    AttackConfig("grey-appearance", "grey", ("color", "transparency"), LR_APPEARANCE,
                 description="grey particles, colour and transparency"),
    AttackConfig("grey-all", "grey", OPTIMIZABLE, LR_POSITIONS,
                 description="grey particles, every variable"),
    AttackConfig("snow", "snow", OPTIMIZABLE, LR_POSITIONS, description="adversarial snow"),
    AttackConfig("rain", "rain", OPTIMIZABLE, LR_POSITIONS, description="adversarial rain"),
    AttackConfig("sparks", "sparks", OPTIMIZABLE, LR_POSITIONS, description="adversarial sparks"),
    AttackConfig("fog", "fog", ("offset1", "color", "transparency"), LR_POSITIONS,
                 occlusion_gradient=True,
                 description="adversarial fog: second offset fixed, gradient through occlusion"),
)


def attack_config(name: str) -> AttackConfig:
    """The configuration called ``name``; ConfigError lists the known ones."""
    try:
        return ATTACK_CONFIGS[name]
    except KeyError:
        raise ConfigError(f"unknown attack configuration {name!r}; known: "
                          f"{', '.join(ATTACK_CONFIGS)}") from None
