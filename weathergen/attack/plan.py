"""The rules that turn an attack request into settings: which configuration, preset and values win.

Precedence, as the command line applies it:

1. a named configuration (``config_name``) sets the preset, the freed variables, the learning
   rate and the gradient through occlusion;
2. explicit values win over it: ``preset``, ``optimize``, ``lr``, ``occlusion_gradient``;
3. the learning rate of a configuration applies only while its own variables are freed
   (otherwise :func:`~weathergen.attack.default_lr` picks one for the variables);
4. without a named configuration, the preset attacked picks one when it has one (``fog`` keeps
   its second offset fixed and differentiates through occlusion, however its particles were
   obtained);
5. stored particles (``particles_from``) fix the preset: another ``preset`` is refused, and so is
   any override (re-render them instead); the paper's published weather (a set of the research
   code's files) is attacked with the preset given, or the one the set's name says, overrides
   allowed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional, Sequence

from ..engine import BETA_ATTACK, BETA_RENDER, CombinedPreset, FieldPreset, Preset
from ..errors import ConfigError
from ..render.plan import resolve_preset
from .compat import transparency_bound_for
from .configs import ATTACK_CONFIGS, AttackConfig, attack_config
from .settings import (DEFAULT_ALPHA, DEFAULT_STEPS, AttackSettings, default_optimize,
                       parse_group_lr, parse_optimize)


@dataclass(frozen=True)
class AttackPlan:
    """What an attack request resolves to.

    config: the configuration that applies (the named one, else the preset's own, else None);
    label: what names the run (the named configuration, else the preset).
    """

    preset: Preset
    preset_name: str
    config: Optional[AttackConfig]
    settings: AttackSettings
    label: str


def plan_attack(config_name: Optional[str] = None, preset: Optional[str] = None,
                overrides: Optional[Mapping[str, str]] = None,
                particles_from: Optional[str | Path] = None, *,
                optimize: Optional[str | Sequence[str]] = None, lr: Optional[float] = None,
                occlusion_gradient: Optional[bool] = None, steps: int = DEFAULT_STEPS,
                alpha1: float = DEFAULT_ALPHA, alpha2: float = DEFAULT_ALPHA,
                compat: str = "paper",
                layers: Optional[str | Sequence[str]] = None,
                group_lr: Optional[str | Sequence[str]] = None,
                sequence: bool = False) -> AttackPlan:
    """Resolve an attack request by the rules of this module; None means "not given".

    ``compat``: ``paper`` or ``reference`` (:mod:`weathergen.attack.compat`); it also picks the
    transparency bound of the preset.

    ``optimize`` is ``"offset1,color"`` (or ``"all"``) or a sequence of variable names.
    ``layers``: for a combined preset, the layers whose variables are freed (``"fog-light"``,
    ``"snow,fog"``, a sequence of names, or ``"all"``/None: every layer). ``group_lr``: rates of
    single learning-rate groups (``"density=0.1"``, or a sequence of such), which win over
    ``lr``; the groups given none take ``lr``, else the configuration's, else the defaults: the
    paper's for a preset with a paper layer, :data:`~weathergen.attack.settings.FIELD_LR` for
    weather fields (the atmosphere's always). ``sequence``: one weather for whole scenes
    (:mod:`~weathergen.attack.sequence`), whose default variables leave out ``offset2``.
    Raises ConfigError for an unknown configuration, preset or variable, and for the refused
    combinations with ``particles_from``.
    """
    named = attack_config(config_name) if config_name else None
    # None: snow, or for the paper's published weather the preset its set's name says
    chosen = preset or (named.preset if named else None)
    resolved = resolve_preset(chosen, None, overrides, particles_from)
    name = resolved.name
    if resolved.appearance:
        raise ConfigError("${overrides} cannot change stored particles in an attack; re-render "
                          "them with `weathergen render --particles` instead")
    if particles_from is not None and preset is not None and preset != name:
        raise ConfigError(f"${{preset}} {preset}: the particles in {particles_from} were sampled "
                          f"from {name!r}; leave ${{preset}} out to attack them")
    config = named if named is not None else ATTACK_CONFIGS.get(name)
    if optimize is None:
        variables = config.optimize if config else default_optimize(resolved.preset)
        if sequence:        # a world weather: one position per particle and frame
            variables = tuple(v for v in variables if v != "offset2")
    else:
        variables = parse_optimize(optimize if isinstance(optimize, str) else ",".join(optimize))
    if lr is None and config is not None and variables == config.optimize:
        lr = config.lr
    if occlusion_gradient is None:
        occlusion_gradient = bool(config and config.occlusion_gradient)
    parts = resolved.preset.layers if isinstance(resolved.preset, CombinedPreset) else (resolved.preset,)
    settings = AttackSettings(optimize=variables, steps=steps, lr=lr, alpha1=alpha1,
                              alpha2=alpha2, beta=BETA_ATTACK if occlusion_gradient else BETA_RENDER,
                              transparency_max=transparency_bound_for(resolved.preset, compat),
                              compat=compat, layers=parse_layers(layers, resolved.preset),
                              group_lr=parse_group_lr(group_lr or ()),
                              lr_defaults="field" if all(isinstance(p, FieldPreset) for p in parts)
                              else "paper")
    return AttackPlan(resolved.preset, name, config, settings, config_name or name)


def parse_layers(layers: Optional[str | Sequence[str]], preset) -> Optional[tuple[str, ...]]:
    """The layers an attack frees (None: every layer), checked against ``preset``'s layers.
    Raises ConfigError for a preset that is not combined or a name that is not one of its
    layers."""
    if layers is None:
        return None
    names = [n.strip() for n in (layers.split(",") if isinstance(layers, str) else layers)
             if n.strip()]
    if not isinstance(preset, CombinedPreset):
        raise ConfigError(f"${{optimize_layer}} {','.join(names)}: applies to combined presets "
                          f"(layers joined by +); {getattr(preset, 'name', 'this preset')} has one")
    if names == ["all"]:
        return None
    if not names:
        raise ConfigError("${optimize_layer}: name at least one layer, or 'all'")
    unknown = [n for n in names if n not in preset.layer_names]
    if unknown:
        raise ConfigError(f"${{optimize_layer}} {', '.join(unknown)}: no such layer of "
                          f"{preset.name} (layers: {', '.join(preset.layer_names)}, or all)")
    return tuple(n for n in preset.layer_names if n in names)


def default_attack_out(label: str) -> Path:
    """Where an attack writes when no folder is given: ``out/attack-<label>``."""
    return Path("out") / f"attack-{label}"


def attack_pass_name(preset_name: str, input_pass: str) -> str:
    """The output pass of an attack: ``<preset>_adv_<input pass>``, e.g. ``snow_adv_clean``."""
    return f"{preset_name}_adv_{input_pass}"
