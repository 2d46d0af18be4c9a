"""Weather presets: validated TOML files describing one particle configuration each.

A preset is a flat table of keys (see :class:`Preset` for every key, its type, range and unit).
Values are resolved in this order, later ones winning:

1. the schema defaults declared on :class:`Preset`;
2. the preset file (a bundled one, by name, or a user's ``.toml`` file, by path);
3. overrides (the parameter ``overrides``), ``{"key": "value"}`` strings as typed on the
   command line (``--set count=500``),
   parsed as TOML values and then validated like the file. A paper preset's count is given for
   Sintel's 1024x436 frames and scaled to each frame's area at sampling (:func:`frame_scaling`);
   an override of ``count`` (or ``size``) means exactly that value on every frame size (it turns
   ``scale_count``, or ``scale_size``, off unless the overrides set those too).

Every problem (unknown key, wrong type, out-of-range value, unknown preset name) raises
:class:`~weathergen.errors.ConfigError` naming the file, the key and the offending value.

Presets of either model joined by ``+`` (``rain-heavy+fog-light``) form a
:class:`CombinedPreset`: one layer per preset, each resolved as above, overrides addressed to a
layer by its name or position (``fog-light.density=0.05``, ``2.density=0.05``; see
:func:`load_combined`).
Here: loading and combined presets; the key schema, the paper's and the field presets have a
module each (:mod:`.preset_schema`, :mod:`.paper_presets`, :mod:`.field_presets`).
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Mapping, Optional

from ...errors import ConfigError
from ...io.text import read_text_file
from .field_presets import FIELD_KEYS, FieldPreset, build_field_preset, field_preset_keys
from .paper_presets import (EXACT_WHEN_GIVEN, PAPER_KEYS, REFERENCE_FRAME, UNSCALED, FrameScaling,
                            Preset, check_consistency, check_template_folder, frame_scaling,
                            parse_override, preset_keys, preset_values, scaled_count, scaled_size)
from .preset_schema import BLEND_MODES, SHARED_KEYS, UNITLESS, Plausible, PlausibleBy

#: Every preset module's names, read from here: the one module to import presets from.
__all__ = ["BLEND_MODES", "EXAMPLE_COMBINATIONS", "LAYER_JOIN", "REFERENCE_FRAME", "SHARED_KEYS",
           "UNITLESS", "UNSCALED", "CombinedPreset", "FieldPreset", "FrameScaling", "Plausible",
           "PlausibleBy", "Preset", "field_preset_keys", "frame_scaling", "list_presets",
           "load_combined", "load_preset", "parse_override", "parse_set_options",
           "preset_file_model", "preset_from_values", "preset_keys", "preset_model",
           "scaled_count", "scaled_size"]


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


def _preset_dir():
    return resources.files("weathergen.presets")


def list_presets(model: Optional[str] = None) -> list[str]:
    """Names of the bundled presets, sorted; only those of one model (``"paper"`` or
    ``"field"``) when ``model`` is given."""
    names = sorted(p.name[:-5] for p in _preset_dir().iterdir() if p.name.endswith(".toml"))
    if model is None:
        return names
    return [n for n in names if preset_file_model(n) == model]


def preset_file_model(name: str) -> str:
    """The model a bundled preset uses, from its ``model`` key (default ``"paper"``)."""
    res = _preset_dir() / f"{name}.toml"
    return str(_read_toml(res.read_text(encoding="utf-8"), res.name).get("model", "paper"))


def _read_toml(text: str, where: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}") from None


def load_preset(name_or_path: str | Path = "snow",
                overrides: Optional[Mapping[str, Any]] = None):
    """Load a bundled preset by name, or a user's preset file by path, and apply overrides.

    ``overrides`` maps keys to values; strings are parsed per the key's type (as for ``--set``),
    other values are type-checked as given. A relative ``templates`` folder in a user file is
    resolved against the file's folder. A file with ``model = "field"`` is a weather-field preset
    and loads as :class:`FieldPreset`; others are the paper's model, :class:`Preset`. Presets
    joined by ``+`` (``"rain-heavy+fog-light"``) load as a :class:`CombinedPreset`, one layer
    each (see :func:`load_combined` for its overrides).
    """
    text_name = str(name_or_path)
    path = Path(text_name)
    if not isinstance(name_or_path, Path) and LAYER_JOIN in text_name and not path.is_file():
        return load_combined(text_name, overrides)
    if isinstance(name_or_path, Path) or text_name.endswith(".toml") or path.is_file():
        if not path.is_file():
            raise ConfigError(f"{path}: preset file does not exist")
        where, name = str(path), path.stem
        data = _read_toml(read_text_file(path, "preset"), where)
        base_dir: Optional[Path] = path.parent
    else:
        known = list_presets()
        if text_name not in known:
            raise ConfigError(f"unknown preset '{text_name}' (known presets: {', '.join(known)})")
        res = _preset_dir() / f"{text_name}.toml"
        where, name = f"preset {text_name} ({res.name})", text_name
        data = _read_toml(res.read_text(encoding="utf-8"), where)
        base_dir = None

    model = data.pop("model", "paper")
    overrides = dict(overrides or {})
    if "model" in overrides:          # a stored preset's values name their model: the same
        wanted = str(overrides.pop("model")).strip().strip('"')
        if wanted not in ("paper", "field"):
            raise ConfigError(f"{where}: key 'model' = {wanted!r}: must be paper or field")
        if wanted != model:
            others = ", ".join(n for n in list_presets(wanted) if "-" not in n
                               or n.endswith("-moderate"))
            raise ConfigError(f"{where}: key 'model' = {wanted!r}: {name} is a {model} preset, "
                              f"and an override cannot change its model (every key would fall "
                              f"back to the other model's defaults); choose a {wanted} preset "
                              f"instead{f' ({others}, ...)' if others else ''}")
    if model == "field":
        return build_field_preset(name, where, data, overrides, base_dir)
    if model != "paper":
        raise ConfigError(f"{where}: key 'model' = {model!r}: must be paper or field")
    values, templates_from = preset_values(where, data, overrides, base_dir, PAPER_KEYS)
    for key, switch in EXACT_WHEN_GIVEN.items():   # --set count=N: exactly N on every frame
        if key in overrides and switch not in overrides:
            values[switch] = False
    preset = Preset(name=name, source=where, **values)
    check_consistency(preset, where)
    check_template_folder(preset.templates, templates_from)
    return preset


def parse_set_options(items: list[str] | tuple[str, ...]) -> dict[str, str]:
    """Turn ``["count=500", "blend=alpha"]`` into ``{"count": "500", "blend": "alpha"}``."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"${{overrides}} {item!r}: expected KEY=VALUE")
        out[key.strip()] = value
    return out


def _layer_label(part: str) -> str:
    """The name a layer written as ``part`` will have: a bundled name, or a file's stem."""
    path = Path(part)
    return path.stem if part.endswith(".toml") or path.is_file() else part


def load_combined(text: str, overrides: Optional[Mapping[str, Any]] = None) -> CombinedPreset:
    """Load presets joined by ``+`` (``"rain-heavy+fog-light"``) as a :class:`CombinedPreset`.

    Each part is a bundled preset's name or a preset file's path, of either model. An override
    key names the layer it is for by name or by 1-based position (``"fog-light.density"``,
    ``"2.density"``); a key without a layer applies to every layer and must be a key of each
    (``"color"``, or ``"frame_rate"`` when every layer is a field preset).

    Raises ConfigError naming ``${preset}`` for an empty layer (``"snow+"``), an unknown preset, a
    layer given twice (its overrides and its particles would be ambiguous: raise its count or
    density instead), and field layers of different frame rates (their motions would not share
    one clock); naming ``${overrides}`` for an override of no layer.
    """
    parts, labels = _layer_parts(text)
    name = LAYER_JOIN.join(labels)

    def load(i: int, sets: Mapping[str, Any]):
        try:
            return load_preset(parts[i], sets)
        except ConfigError as exc:
            # args[0] keeps the ${parameter} marks for the command line to spell
            raise ConfigError(f"${{preset}} {name}: layer {i + 1} ({labels[i]}): {exc.args[0]}"
                              ) from None

    plain = [load(i, {}) for i in range(len(parts))]      # each layer's model and schema
    per_layer = _layer_overrides(overrides or {}, plain, labels, name)
    layers = tuple(load(i, sets) if sets else plain[i] for i, sets in enumerate(per_layer))
    rates = {p.name: p.frame_rate for p in layers if isinstance(p, FieldPreset)}
    if len(set(rates.values())) > 1:
        listed = ", ".join(f"{n} {r:g}" for n, r in rates.items())
        raise ConfigError(f"${{preset}} {name}: its field layers have different frame rates "
                          f"(frame_rate: {listed}; 0 is the dataset's), so their motions would "
                          "not share one clock; give them one (${overrides} LAYER.frame_rate=...)")
    return CombinedPreset(layers, name, "; ".join(p.source for p in layers))


def _layer_parts(text: str) -> tuple[list[str], list[str]]:
    """The parts of a combined preset's name (``"rain-heavy+fog-light"``) and the names its
    layers will have. Raises ConfigError naming ``${preset}`` for an empty part or a layer given
    twice."""
    parts = [p.strip() for p in text.split(LAYER_JOIN)]
    for i, part in enumerate(parts, 1):
        if not part:
            raise ConfigError(f"${{preset}} {text}: layer {i} of {len(parts)} is empty; join "
                              f"preset names with {LAYER_JOIN}, e.g. rain-heavy+fog-light")
    labels = [_layer_label(p) for p in parts]
    for label in labels:
        if labels.count(label) > 1:
            raise ConfigError(f"${{preset}} {text}: layer {label!r} is given twice; a preset is one "
                              "layer (raise its count or density instead)")
    return parts, labels


def _layer_overrides(overrides: Mapping[str, Any], plain: list, labels: list[str],
                     name: str) -> list[dict]:
    """The overrides of each layer of combined preset ``name`` (see :func:`load_combined`):
    ``LAYER.key`` (a layer's name or 1-based position) for that layer, a bare key for every layer
    (``plain``: the layers' presets without overrides, whose schemas must all have it). Raises
    ConfigError naming ``${overrides}`` for an override of no layer."""
    per_layer: list[dict] = [{} for _ in labels]
    for key, value in overrides.items():
        prefix, dot, bare = str(key).rpartition(".")
        if dot:
            if prefix.isdigit() and 1 <= int(prefix) <= len(labels):
                per_layer[int(prefix) - 1][bare] = value
            elif prefix in labels:
                per_layer[labels.index(prefix)][bare] = value
            else:
                listed = ", ".join(f"{i} {label}" for i, label in enumerate(labels, 1))
                raise ConfigError(f"${{overrides}} {key}: {name} has no layer {prefix!r} "
                                  f"(layers: {listed}; name one or give its position)")
            continue
        # every preset file may name its model: each layer checks a bare ``model`` itself
        lacking = [i for i, p in enumerate(plain) if key != "model"
                   and key not in (FIELD_KEYS if isinstance(p, FieldPreset) else PAPER_KEYS)]
        if len(lacking) == len(labels):
            raise ConfigError(f"${{overrides}} {key}: no layer of {name} has this key "
                              f"(`weathergen presets {name}` lists their keys)")
        if lacking:
            i = lacking[0]
            having = next(label for j, label in enumerate(labels) if j not in lacking)
            raise ConfigError(f"${{overrides}} {key}: not a key of layer {i + 1} ({labels[i]}, a "
                              f"{preset_model(plain[i])} preset); name the layer it is for, e.g. "
                              f"{having}.{key}=...")
        for sets in per_layer:
            sets[key] = value
    return per_layer
