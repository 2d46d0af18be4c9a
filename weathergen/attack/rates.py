"""Adam with one learning rate per group of variables (:data:`~weathergen.attack.settings.LR_GROUPS`):
the freed variables of an attack sorted into their groups, and the optimiser over them."""

from __future__ import annotations

from typing import Sequence

import torch

from .settings import AttackSettings, lr_group


def variable_groups(variables) -> dict[str, list[torch.Tensor]]:
    """Every freed variable of a :class:`~weathergen.attack.WeatherVariables` (or of each freed
    layer of a ``LayeredVariables``, its ``freed``) by its learning-rate group."""
    out: dict[str, list[torch.Tensor]] = {}
    for v in (variables.freed.values() if hasattr(variables, "freed") else (variables,)):
        for name, p in (*v.delta.items(), *v.atmosphere.items()):
            out.setdefault(lr_group(name), []).append(p)
    return out


def group_optimizer(variables: Sequence, settings: AttackSettings) -> torch.optim.Adam:
    """Adam over the freed variables of ``variables`` (:class:`~weathergen.attack.WeatherVariables` or
    ``LayeredVariables``), one parameter group per learning-rate group, named ``group``,
    at the rate :attr:`AttackSettings.learning_rates` gives it."""
    joined: dict[str, list[torch.Tensor]] = {}
    for v in variables:
        for group, params in variable_groups(v).items():
            joined.setdefault(group, []).extend(params)
    rates = settings.learning_rates
    groups = [{"params": params, "lr": rates[group], "group": group}
              for group, params in joined.items()]
    # (no variable at all, e.g. nothing visible: an empty group keeps Adam's constructor happy)
    return torch.optim.Adam(groups or [{"params": [], "group": "none"}], lr=1.0)
