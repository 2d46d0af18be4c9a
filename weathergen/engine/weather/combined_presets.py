"""Combined presets: several presets of either model in one scene, one layer each
(:class:`CombinedPreset`), and a preset of either model rebuilt from its stored values
(:func:`preset_from_values`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

from ...errors import ConfigError
from .field_presets import build_field_preset
from .paper_presets import PAPER_KEYS, Preset, check_consistency, check_template_folder, preset_values

# ---------------------------------------------------------------------------------------------
# Combined presets: several presets in one scene, one layer each.

#: The character that joins presets into a combined preset: ``rain-heavy+fog-light``.
LAYER_JOIN = "+"
#: Combinations ``weathergen presets`` lists as examples (any presets of either model combine).
EXAMPLE_COMBINATIONS = {
    "rain-heavy+fog-light": "a downpour in light fog",
    "snow-moderate+fog-light": "snowfall in light fog",
    "snow-light+fog-moderate": "light snow in moderate fog",
    "rain-moderate+snow-light": "sleet: rain and a little snow",
    "sparks-moderate+fog-moderate": "sparks in smoke",
    "snow+fog": "the paper's snow and fog presets in one pair",
}


@dataclass(frozen=True)
class CombinedPreset:
    """Several presets of either model rendered into one scene, one *layer* each.

    ``layers`` holds each layer's preset (:class:`Preset` or :class:`FieldPreset`), fully resolved
    with its own overrides, in the order written; a layer is named by its preset's ``name`` (a
    bundled preset's name or a preset file's stem), unique within the combination. Every layer
    keeps its own values: a combination never rescales a layer, so ``snow-light+fog-moderate``
    has the density of ``snow-light`` and of ``fog-moderate``, and a severity ladder keeps its
    ratios in combination.
    """

    layers: tuple
    name: str = field(default="", compare=False)
    source: str = field(default="", compare=False)

    model = "combined"

    def __post_init__(self):
        if len(self.layers) < 2:
            raise ConfigError(f"a combined preset needs two layers or more, got {len(self.layers)}")
        names = self.layer_names
        if len(set(names)) != len(names):
            raise ConfigError(f"combined preset {self.name or LAYER_JOIN.join(names)}: layer names "
                              f"must differ, got {', '.join(names)}")

    @property
    def layer_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.layers)

    @property
    def layer_models(self) -> tuple[str, ...]:
        """``"paper"`` or ``"field"`` per layer."""
        return tuple(preset_model(p) for p in self.layers)

    def layer(self, which: int | str):
        """A layer's preset, by position (0-based) or name."""
        if isinstance(which, str):
            if which not in self.layer_names:
                raise ConfigError(f"combined preset {self.name}: no layer {which!r} "
                                  f"(layers: {', '.join(self.layer_names)})")
            return self.layers[self.layer_names.index(which)]
        return self.layers[which]

    def to_dict(self) -> dict:
        """``name``, ``source``, ``model`` (``"combined"``) and ``layers``: every layer's
        ``to_dict()`` (for manifests and metadata; :meth:`from_dict` reads it back)."""
        return {"name": self.name, "source": self.source, "model": self.model,
                "layers": [p.to_dict() for p in self.layers]}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "CombinedPreset":
        """The combined preset a :meth:`to_dict` dictionary records, every value validated again.
        Raises ConfigError naming the layer on a missing or invalid entry."""
        layers = data.get("layers")
        if not isinstance(layers, list) or not all(isinstance(d, Mapping) for d in layers):
            raise ConfigError(f"stored combined preset {data.get('name', '?')!r}: no list of layers")
        out = []
        for i, layer in enumerate(layers, 1):
            values = {k: v for k, v in layer.items() if k not in ("name", "source")}
            name = str(layer.get("name", f"layer{i}"))
            out.append(preset_from_values(name, str(layer.get("source", f"stored layer {i}")),
                                          values))
        return cls(tuple(out), str(data.get("name", LAYER_JOIN.join(p.name for p in out))),
                   str(data.get("source", "")))


def preset_model(preset) -> str:
    """``"paper"``, ``"field"`` or ``"combined"``: the model a loaded preset belongs to."""
    return getattr(preset, "model", "paper")


def preset_from_values(name: str, where: str, values: Mapping[str, Any]):
    """A preset of either model from every key's value (a ``to_dict()`` without ``name`` and
    ``source``; ``model`` picks the schema, default paper), validated as a preset file is."""
    values = dict(values)
    model = values.pop("model", "paper")
    if model == "field":
        return build_field_preset(name, where, values, {}, None)
    if model != "paper":
        raise ConfigError(f"{where}: key 'model' = {model!r}: must be paper or field")
    checked, templates_from = preset_values(where, values, {}, None, PAPER_KEYS)
    preset = Preset(name=name, source=where, **checked)
    check_consistency(preset, where)
    check_template_folder(preset.templates, templates_from)
    return preset


