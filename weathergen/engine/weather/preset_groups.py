"""The bundled presets in the groups a reader of the paper knows them by.

- the paper's four weathers (snow, rain, sparks, fog: the defaults its Table 1 highlights);
- its ablation variants: the other rows of its "Particle configurations" table (supplement), each
  varying one parameter of the particles (count, motion blur length, size, colour with additive or
  alpha blending) or giving the grey particles of the optimised-variables ablation (Table 2);
- the weather-field severity ladders (each weather light, moderate, heavy);
- presets found in the preset folder that belong to none of these, per model.

``weathergen presets`` lists them in this order; the example combinations are
:data:`~weathergen.engine.weather.presets.EXAMPLE_COMBINATIONS`.
"""

from __future__ import annotations

from dataclasses import dataclass

from .presets import list_presets

#: The paper's four weathers, in its order.
PAPER_WEATHERS = ("snow", "rain", "sparks", "fog")
#: The paper's ablation variants by family: (name, or name prefix ending in "-", what it varies;
#: ``grey`` gives the particles of the optimised-variables ablation, the paper's Table 2).
ABLATIONS = (("particles-", "count"),
             ("motion-blur-", "blur length"),
             ("size-", "size"),
             ("additive-", "colour, additive"),
             ("alpha-", "colour, alpha"),
             ("grey", "grey: Table 2"))
#: The severities of a weather-field ladder, lightest first.
SEVERITIES = ("light", "moderate", "heavy")


@dataclass(frozen=True)
class PresetGroup:
    """Presets of one model shown together: ``names`` in order, ``varies`` beside each (what an
    ablation variant varies; empty for other groups)."""

    title: str
    model: str
    names: tuple[str, ...]
    varies: tuple[str, ...] = ()


def _family(name: str) -> int | None:
    """The index in :data:`ABLATIONS` of ``name``'s family, or None."""
    for i, (key, _) in enumerate(ABLATIONS):
        if (name.startswith(key) if key.endswith("-") else name == key):
            return i
    return None


def _ladder_place(name: str) -> tuple[int, int] | None:
    """(weather, severity) of a ladder preset such as ``rain-moderate``, or None."""
    weather, _, severity = name.rpartition("-")
    if weather in PAPER_WEATHERS and severity in SEVERITIES:
        return PAPER_WEATHERS.index(weather), SEVERITIES.index(severity)
    return None


def preset_groups() -> tuple[PresetGroup, ...]:
    """Every bundled preset in exactly one group (see the module doc); empty groups are left out."""
    paper, field = list_presets("paper"), list_presets("field")
    weathers = tuple(n for n in PAPER_WEATHERS if n in paper)
    variants = sorted((n for n in paper if n not in weathers and _family(n) is not None),
                      key=lambda n: (_family(n), n))
    ladder = sorted((n for n in field if _ladder_place(n) is not None), key=_ladder_place)
    groups = [
        PresetGroup("the paper's four weathers", "paper", weathers),
        PresetGroup("the paper's ablation variants (its particle configurations)", "paper",
                    tuple(variants), tuple(ABLATIONS[_family(n)][1] for n in variants)),
        PresetGroup("weather fields: severity ladders", "field", tuple(ladder)),
        PresetGroup("other paper presets", "paper",
                    tuple(n for n in paper if n not in weathers and n not in variants)),
        PresetGroup("other weather fields", "field", tuple(n for n in field if n not in ladder)),
    ]
    return tuple(g for g in groups if g.names)
