"""Attack configurations: named settings of the paper's supplement (preset, freed variables,
learning rate, gradient through occlusion), read from data files like the presets.

The bundled configurations are the tables of ``weathergen/presets/attacks/*.toml`` (files in name
order, tables in file order). A table holds ``preset`` and ``optimize`` and may hold ``lr``
(default: :func:`~weathergen.attack.default_lr` of the variables), ``occlusion_gradient``
(default false) and ``description``. Every problem raises ConfigError naming the file and table.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from typing import Any

from ..errors import ConfigError
from .settings import OPTIMIZABLE, default_lr


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


_KEYS = ("preset", "optimize", "lr", "occlusion_gradient", "description")


def parse_configs(text: str, where: str) -> dict[str, AttackConfig]:
    """The configurations of one TOML text (``where`` names it in messages), in table order."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}") from None
    out = {}
    for name, table in data.items():
        here = f"{where}: [{name}]"
        if not isinstance(table, dict):
            raise ConfigError(f"{here}: expected a table of {', '.join(_KEYS)}")
        unknown = sorted(set(table) - set(_KEYS))
        if unknown:
            raise ConfigError(f"{here}: unknown key(s) {', '.join(unknown)}; known: {', '.join(_KEYS)}")
        out[name] = _config(name, table, here)
    return out


def _config(name: str, table: dict[str, Any], here: str) -> AttackConfig:
    preset = table.get("preset")
    if not isinstance(preset, str) or not preset:
        raise ConfigError(f"{here}: 'preset' must name a preset")
    optimize = table.get("optimize")
    if (not isinstance(optimize, list) or not optimize
            or any(v not in OPTIMIZABLE for v in optimize)):
        raise ConfigError(f"{here}: 'optimize' must list some of {', '.join(OPTIMIZABLE)}")
    variables = tuple(v for v in OPTIMIZABLE if v in optimize)
    lr = table.get("lr", default_lr(variables))
    if isinstance(lr, bool) or not isinstance(lr, (int, float)) or not (lr > 0 and math.isfinite(lr)):
        raise ConfigError(f"{here}: 'lr' must be a positive number")
    occlusion = table.get("occlusion_gradient", False)
    if not isinstance(occlusion, bool):
        raise ConfigError(f"{here}: 'occlusion_gradient' must be true or false")
    description = table.get("description", "")
    if not isinstance(description, str):
        raise ConfigError(f"{here}: 'description' must be a string")
    return AttackConfig(name, preset, variables, float(lr), occlusion, description)


def _bundled() -> dict[str, AttackConfig]:
    folder = resources.files("weathergen.presets") / "attacks"
    configs: dict[str, AttackConfig] = {}
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            for name, config in parse_configs(entry.read_text(encoding="utf-8"),
                                              f"attacks/{entry.name}").items():
                if name in configs:
                    raise ConfigError(f"attacks/{entry.name}: [{name}] is defined twice")
                configs[name] = config
    return configs


#: The bundled configurations by name, in the order of their files and tables.
ATTACK_CONFIGS: dict[str, AttackConfig] = _bundled()


def attack_config(name: str) -> AttackConfig:
    """The configuration called ``name``; ConfigError lists the known ones."""
    try:
        return ATTACK_CONFIGS[name]
    except KeyError:
        raise ConfigError(f"unknown attack configuration {name!r}; known: "
                          f"{', '.join(ATTACK_CONFIGS)}") from None
