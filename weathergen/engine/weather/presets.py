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
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Mapping, Optional

from ...errors import ConfigError, WeatherGenError
from ...io.text import read_text_file
from .atmosphere import rain_extinction, snow_extinction, visibility_extinction
from .optics import FieldOptics
from .templates import BUILTIN_TEMPLATE_KINDS, load_templates

BLEND_MODES = ("additive", "alpha")
TRANSPARENCY_MODES = ("depth", "constant")


# ---------------------------------------------------------------------------------------------
# Checks: each returns an error text (what the value must be) or None when the value is fine.

def _number(lo: float = -math.inf, hi: float = math.inf, *, lo_open: bool = False
            ) -> Callable[[Any], Optional[str]]:
    def check(v):
        if not math.isfinite(v):
            return "must be a finite number"
        if v < lo or (lo_open and v == lo) or v > hi:
            left = "(" if lo_open else "["
            return f"must lie in {left}{lo:g}, {hi:g}]"
        return None
    return check


def _odd_size(v: int) -> Optional[str]:
    if v < 1 or v % 2 == 0:
        return "must be an odd number of pixels >= 1 (templates are centred on a pixel)"
    if v > 2047:
        return "must be at most 2047 pixels"
    return None


def _count(v: int) -> Optional[str]:
    return "must be a count >= 0" if v < 0 else ("must be at most 1000000" if v > 1_000_000 else None)


def _rgb(v: tuple) -> Optional[str]:
    if len(v) != 3:
        return "must be three integers (R, G, B)"
    if any(c < 0 or c > 255 for c in v):
        return "must be three integers in [0, 255]"
    return None


def _interval(v: tuple) -> Optional[str]:
    if len(v) != 2 or not all(math.isfinite(x) for x in v):
        return "must be two finite numbers [min, max]"
    if not v[0] < v[1]:
        return "must satisfy min < max"
    return None


def _choice(options: tuple[str, ...]) -> Callable[[str], Optional[str]]:
    return lambda v: None if v in options else f"must be one of {', '.join(options)}"


def _templates(v: str) -> Optional[str]:
    return None if v.strip() else f"must be {' or '.join(BUILTIN_TEMPLATE_KINDS)} or a folder of PNGs"


# ---------------------------------------------------------------------------------------------
# Plausible ranges: a key in physical units declares the range its values plausibly lie in. A value
# outside it that the key's check allows is most often a slip of unit (millimetres written as
# metres, km/h as m/s), which would draw absurd weather or exhaust the memory: refused in one line
# that names the key, the range and the slip.

@dataclass(frozen=True)
class Plausible:
    """The range ``[lo, hi]`` (in ``unit``) a key's values plausibly lie in (``zero``: 0 is
    allowed too, as a switch: no streak, the dataset's frame rate), and the unit slips worth
    naming: ``(factor, unit given)``, where ``value * factor`` is the value meant when it was
    written in ``unit given`` (8 for 0.008 m: ``(0.001, "millimetres")``)."""

    lo: float
    hi: float
    unit: str
    slips: tuple = ()
    zero: bool = False
    what: str = ""              # whose range this is, where a key has several (see PlausibleBy)

    def problem(self, value: float) -> Optional[str]:
        """What is wrong with ``value`` (None when it is plausible), in a few words."""
        if self.lo <= value <= self.hi or (self.zero and value == 0):
            return None
        unit = f" {self.unit}" if self.unit else ""
        text = (f"{value:g}{unit} is outside the plausible {self.lo:g} to {self.hi:g}{unit}"
                f"{' (or 0)' if self.zero else ''}{f' for {self.what}' if self.what else ''}")
        return text + self.slip(value)

    def slip(self, value: float) -> str:
        """``"; did you mean 0.008 m (8 mm)?"`` where ``value`` written in one of the ``slips``'
        units lies in the range, else ``""``."""
        for factor, given in self.slips:
            meant = value * factor
            if self.lo <= meant <= self.hi and meant != value:
                unit = f" {self.unit}" if self.unit else ""
                return f"; did you mean {meant:.4g}{unit} ({value:g} {given})?"
        return ""


@dataclass(frozen=True)
class PlausibleBy:
    """Plausible ranges that depend on another key's value (``key``): ``ranges`` maps its values
    to a :class:`Plausible`, ``other`` holds for any other value."""

    key: str
    ranges: Mapping[str, Plausible]
    other: Plausible

    def range_for(self, preset) -> Plausible:
        return self.ranges.get(str(getattr(preset, self.key)), self.other)


#: The plausible range of a dimensionless key (a jitter, a fraction, an angle, a count) is the
#: range its check allows: declared so, so that every numeric key says which it is.
UNITLESS = "unitless"

#: Unit slips of lengths in metres, speeds in m/s and times in seconds.
LENGTH_SLIPS = ((0.001, "mm"), (0.01, "cm"))
SPEED_SLIPS = ((1 / 3.6, "km/h"),)
TIME_SLIPS = ((0.001, "ms"),)
#: Distances in metres written in kilometres (a visibility of 0.3 for 300 m).
KM_SLIPS = ((1000, "km"),)


def _key(default, check=None, doc: str = "", main: bool = False, plausible=None, coerce=None):
    """Declare a preset key once: its default, its check, a one-line description, for a key in
    physical units its :class:`Plausible` range (or :data:`UNITLESS`); ``coerce``: for a key of
    several types, a function ``value -> (canonical value, problem or None)`` in place of the type
    check (it then does the check too)."""
    return field(default=default, metadata={"check": check, "doc": doc, "main": main,
                                            "plausible": plausible, "coerce": coerce})


def check_plausible(preset, keys: Mapping[str, dataclasses.Field], where: str,
                    overridden: Mapping[str, Any] = {}) -> None:
    """Refuse a value outside its key's plausible range (see :class:`Plausible`): ConfigError
    naming the key, the value, the range and the likely unit slip, and where the value came from
    (``${overrides}`` for a key in ``overridden``, else ``where``)."""
    for name, f in keys.items():
        plausible = f.metadata.get("plausible")
        if isinstance(plausible, PlausibleBy):
            plausible = plausible.range_for(preset)
        if not isinstance(plausible, Plausible):
            continue
        value = getattr(preset, name)
        for v in (value if isinstance(value, tuple) else (value,)):
            problem = plausible.problem(float(v))
            if problem is not None:
                origin = "${overrides}" if name in overridden else where
                shown = list(value) if isinstance(value, tuple) else value
                raise ConfigError(f"{origin}: key '{name}' = {shown!r}: {problem}")


#: The keys of both weather models (the paper's :class:`Preset` and :class:`FieldPreset`), declared
#: here once: name -> (default, check, description, main, plausible). ``transparency`` and
#: ``blur_samples`` mean something model-specific, which each model's description says.
SHARED_KEYS = {
    "description": ("", None, "free text shown by `weathergen presets`", False, None),
    "templates": ("flakes", _templates,
                  "template library: flakes, dust, haze, or a folder of grey-scale PNGs", True, None),
    "color": ((255, 255, 255), _rgb, "base colour, 8-bit RGB", True, UNITLESS),
    "hue_jitter": (0.0, _number(0, 180), "random hue change, +- degrees", False, UNITLESS),
    "lightness_jitter": (0.0, _number(0, 1), "random HLS lightness change, +-", False, UNITLESS),
    "saturation_jitter": (0.0, _number(0, 1), "random HLS saturation change, +-", False, UNITLESS),
    "blend": ("additive", _choice(BLEND_MODES),
              "additive (glow) or alpha (order-independent alpha blending)", True, None),
    "transparency": (0.75, _number(0, 2), "", True, UNITLESS),
    "blur_samples": (1, _number(1, 1000), "", True, UNITLESS),
    "coarse": (True, None, "draw stamps of at least 128 px (fog, large dust) on a coarser grid "
                           "and upsample them across depth edges (fast, within the tolerance of "
                           "docs/engine.md); false: every pixel exactly", False, None),
}


def _shared(name: str, doc: str = ""):
    """A key of :data:`SHARED_KEYS` (``doc``: the model's own description, where it has one)."""
    default, check, text, main, plausible = SHARED_KEYS[name]
    return _key(default, check, doc or text, main, plausible)


@dataclass(frozen=True)
class Preset:
    """One weather configuration, fully resolved and validated. Every field is a preset key.

    Units: lengths and motions in scene units (those of the frame pair's depth), sizes in pixels,
    angles in degrees, colours as 8-bit RGB.
    """

    description: str = _shared("description")
    # -- particle base properties
    count: int = _key(3000, _count, "particles per frame pair of 1024x436 pixels; other frame "
                                    "sizes scale it by their area (see scale_count)", main=True)
    size: int = _key(71, _odd_size, "template side in pixels at depth <= 1/depth_decay (odd)",
                     main=True)
    scale_count: bool = _key(True, None, "scale count with the frame's area relative to 1024x436, "
                                         "keeping particles per pixel area (false: count on every "
                                         "frame; --set count=N sets it false)")
    scale_size: bool = _key(False, None, "scale size and the defocus radius with the frame's "
                                         "diagonal relative to 1024x436 (with scale_count false: "
                                         "the frame as a resized 1024x436 one; --set size=N sets "
                                         "it false)")
    depth_decay: float = _key(9.0, _number(0, 1e6, lo_open=True),
                              "size scales by min(1, 1/(depth * depth_decay))", main=True)
    templates: str = _shared("templates")
    # -- colour
    color: tuple = _shared("color")
    hue_jitter: float = _shared("hue_jitter")
    lightness_jitter: float = _shared("lightness_jitter")
    saturation_jitter: float = _shared("saturation_jitter")
    blend: str = _shared("blend")
    transparency: float = _shared("transparency",
                                  "theta = this x depth hat (the hat peaks at 0.73), or this value "
                                  "itself when transparency_mode is constant")
    transparency_mode: str = _key("depth", _choice(TRANSPARENCY_MODES),
                                  "depth: hat over depth; constant: theta for every particle")
    # -- motion
    motion_y: float = _key(0.2, _number(-1e3, 1e3),
                           "frame-to-frame fall distance, > 0 falls down, < 0 rises", main=True)
    motion_scale_jitter: float = _key(0.0, _number(0, 1),
                                      "motion length scaled by 1 + U[-f, f]")
    motion_angle_jitter: float = _key(0.0, _number(0, 180),
                                      "motion direction turned by Euler angles U[-a, a] degrees")
    # -- motion blur
    motion_blur: bool = _key(False, None, "render K samples along the 3D motion", main=True)
    blur_length: float = _key(0.0, _number(0, 10),
                              "blur streak as a fraction of the frame-to-frame motion", main=True)
    blur_samples: int = _shared("blur_samples", "samples K per blurred particle")
    # -- out-of-focus blur
    defocus: bool = _key(True, None, "disc blur for particles near the focal distance")
    defocus_brighten: bool = _key(True, None,
                                  "brighten the disc-blurred alpha b to min(1, (2b)^(1/3))")
    coarse: bool = _shared("coarse")
    # -- where particles are sampled, camera-1 coordinates
    volume_x: tuple = _key((-5.0, 5.0), _interval, "sampling box x range, camera 1")
    volume_y: tuple = _key((-5.0, 5.0), _interval, "sampling box y range, camera 1")
    volume_z: tuple = _key((0.0, 3.0), _interval, "sampling box z (depth) range, camera 1")

    # Not keys: where the preset came from (for messages and manifests).
    name: str = field(default="custom", compare=False, metadata={"key": False})
    source: str = field(default="<defaults>", compare=False, metadata={"key": False})

    def to_dict(self) -> dict:
        """Every key with its resolved value, plus ``name`` and ``source`` (for manifests)."""
        return {"name": self.name, "source": self.source, **_key_values(self, preset_keys())}

    @property
    def blur_sample_count(self) -> int:
        """The number of samples actually rendered per particle (1 when motion blur is off)."""
        return self.blur_samples if self.motion_blur else 1

    @property
    def effective_blur_length(self) -> float:
        return self.blur_length if self.motion_blur else 0.0


def _key_values(preset, keys: list[dataclasses.Field]) -> dict:
    """The values of a preset's ``keys``, tuples as lists (as TOML and JSON write them)."""
    out = {}
    for f in keys:
        v = getattr(preset, f.name)
        out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


def preset_keys() -> list[dataclasses.Field]:
    """The schema: every field of :class:`Preset` that a preset file may set."""
    return [f for f in dataclasses.fields(Preset) if f.metadata.get("key", True)]


_KEYS = {f.name: f for f in preset_keys()}


def _coerce(where: str, key: str, value: Any, keys: Optional[Mapping] = None) -> Any:
    """Type-check one value against the schema (``keys``, default :class:`Preset`'s); return it in
    its canonical Python type."""
    keys = _KEYS if keys is None else keys
    f = keys.get(key)
    if f is None:
        raise ConfigError(f"{where}: unknown key '{key}' (known keys: {', '.join(keys)})")
    default = f.default
    bad = lambda what: ConfigError(f"{where}: key '{key}' = {value!r}: {what}")  # noqa: E731
    coerce = f.metadata.get("coerce")
    if coerce is not None:
        out, problem = coerce(value)
        if problem:
            raise bad(problem)
        return out
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("must be true or false")
        out = value
    elif isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                value = int(value)
            else:
                raise bad("must be an integer")
        out = int(value)
    elif isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad("must be a number")
        out = float(value)
    elif isinstance(default, str):
        if not isinstance(value, str):
            raise bad("must be a string")
        out = value
    elif isinstance(default, tuple):
        if not isinstance(value, (list, tuple)):
            raise bad(f"must be a list of {len(default)} values")
        elem = type(default[0])
        items = []
        for x in value:
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                raise bad("must be a list of numbers")
            if elem is int and not float(x).is_integer():
                raise bad("must be a list of integers")
            items.append(elem(x))
        out = tuple(items)
    else:  # pragma: no cover - the schema only holds the types above
        raise TypeError(f"unsupported schema type for {key}")
    check = f.metadata.get("check")
    problem = check(out) if check else None
    if problem:
        plausible = f.metadata.get("plausible")
        if isinstance(plausible, Plausible) and isinstance(out, float):
            problem += plausible.slip(out)
        raise bad(problem)
    return out


def parse_override(key: str, text: str, where: str = "${overrides}",
                   keys: Optional[Mapping] = None) -> Any:
    """Parse a command-line value for ``key`` using the key's type (TOML syntax, bare strings ok).

    ``"500"`` -> 500, ``"true"`` -> True, ``"255,0,0"`` or ``"[255, 0, 0]"`` -> (255, 0, 0).
    """
    keys = _KEYS if keys is None else keys
    if key not in keys:
        raise ConfigError(f"{where}: unknown key '{key}' (known keys: {', '.join(keys)})")
    default = keys[key].default
    raw = text.strip()
    if isinstance(default, tuple) and not raw.startswith("["):
        raw = f"[{raw}]"
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        if isinstance(default, str) and not isinstance(default, bool):
            value = text  # bare strings need no quotes on the command line
        else:
            raise ConfigError(f"{where}: key '{key}' = {text!r}: not a valid "
                              f"{type(default).__name__} value") from None
    if isinstance(default, str) and not isinstance(value, str):
        value = text
    return _coerce(where, key, value, keys)


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
    values, templates_from = _preset_values(where, data, overrides, base_dir, _KEYS)
    for key, switch in EXACT_WHEN_GIVEN.items():   # --set count=N: exactly N on every frame
        if key in overrides and switch not in overrides:
            values[switch] = False
    preset = Preset(name=name, source=where, **values)
    _check_consistency(preset, where)
    _check_template_folder(preset.templates, templates_from)
    return preset


def _preset_values(where: str, data: Mapping[str, Any], overrides: Mapping[str, Any],
                   base_dir: Optional[Path], keys: Mapping[str, dataclasses.Field],
                   ignored: tuple[str, ...] = ()) -> tuple[dict, str]:
    """Type-check a preset file's values (``data``, read from ``where``) and then ``overrides``
    (later ones win) against the schema ``keys``; override keys in ``ignored`` are skipped. A
    relative ``templates`` folder in the file is resolved against ``base_dir`` (None: as given).
    Returns the values and where the ``templates`` value came from (for messages)."""
    values = {}
    templates_from = where
    for key, value in data.items():
        if isinstance(value, dict):
            raise ConfigError(f"{where}: key '{key}' is a table; preset files are flat "
                              f"(known keys: {', '.join(keys)})")
        values[key] = _coerce(where, key, value, keys)
    if base_dir is not None and "templates" in values:
        values["templates"] = _resolve_templates(values["templates"], base_dir)
    for key, value in overrides.items():
        if key in ignored:
            continue
        if isinstance(value, str):
            values[key] = parse_override(key, value, keys=keys)
        else:
            values[key] = _coerce("override", key, value, keys)
        if key == "templates":
            templates_from = "${overrides}" if isinstance(value, str) else "override"
    return values, templates_from


def _check_template_folder(value: str, where: str) -> None:
    """A template folder must exist and hold readable PNGs: say so now, naming the key, rather
    than in the middle of a run."""
    if value in BUILTIN_TEMPLATE_KINDS:
        return
    try:
        load_templates(value)
    except WeatherGenError as exc:
        raise ConfigError(f"{where}: key 'templates' = {value!r}: {exc}") from None


def _resolve_templates(value: str, base_dir: Path) -> str:
    if value in BUILTIN_TEMPLATE_KINDS:
        return value
    p = Path(value).expanduser()
    return str(p if p.is_absolute() else (base_dir / p))


def _check_consistency(p: Preset, where: str) -> None:
    if p.motion_blur and p.blur_length <= 0:
        raise ConfigError(f"{where}: key 'blur_length' = {p.blur_length!r}: must be > 0 "
                          "when motion_blur is true")


# ---------------------------------------------------------------------------------------------
# Frame sizes
# The paper's table gives a number of particles per pair and sizes in pixels, made for Sintel's
# 1024x436 frames. On another frame size a preset keeps the paper's density per pixel area: the
# count scales with the frame's area, sizes stay in pixels, so that the fraction of the frame the
# particles cover stays the paper's too. Scaling the sizes with the frame's diagonal as well would
# change that fraction by the square of the diagonal ratio (1/7 on the 384x176 demo, 4 times on a
# 1920x1080 frame); ``scale_size`` does it for frames that are a resized 1024x436 view (with
# ``scale_count`` off). docs/engine.md, "Frame sizes", says which keys scale and why.

#: The frame size the paper's presets were made for, (height, width): Sintel's.
REFERENCE_FRAME = (436, 1024)
#: The keys given for a :data:`REFERENCE_FRAME` frame, and the switch that scales each of them. An
#: override of the key (``--set count=500``) turns its switch off unless the switch is set too.
EXACT_WHEN_GIVEN = {"count": "scale_count", "size": "scale_size"}
#: What a recorded paper preset without these switches (an output written before they existed)
#: meant: its count and size were used as given on every frame.
UNSCALED = {"scale_count": False, "scale_size": False}


@dataclass(frozen=True)
class FrameScaling:
    """A paper preset's count and pixel sizes on one frame size (see :func:`frame_scaling`).

    ``count`` and ``size`` are the values sampling uses; ``pixel_scale`` multiplies the other
    lengths in pixels fixed at sampling (the defocus radius); ``count_rule`` is ``"area"`` (scaled
    with the frame's area) or ``"fixed"`` (the preset's count on every frame), ``size_rule``
    ``"diagonal"`` or ``"fixed"``; ``preset_count`` and ``preset_size`` are the preset's values.
    """

    height: int
    width: int
    count: int
    size: int
    pixel_scale: float
    count_rule: str
    size_rule: str
    preset_count: int
    preset_size: int

    def to_dict(self) -> dict:
        """Every field, plus the reference frame (as the particle metadata stores it)."""
        return {**dataclasses.asdict(self), "reference": list(REFERENCE_FRAME)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "FrameScaling":
        """The record :meth:`to_dict` wrote (its ``reference`` entry is the constant)."""
        return cls(**{f.name: data[f.name] for f in dataclasses.fields(cls)})

    def describe(self) -> str:
        """One line: the count and size used and where they come from."""
        ref_h, ref_w = REFERENCE_FRAME
        frame = f"{self.width}x{self.height}"
        count = (f"{self.count} particles = {self.preset_count} x area {frame} / {ref_w}x{ref_h}"
                 if self.count_rule == "area" else f"{self.count} particles (fixed)")
        size = (f"size {self.size} px = {self.preset_size} x diagonal ratio {self.pixel_scale:.4g}"
                if self.size_rule == "diagonal" else f"size {self.size} px (fixed)")
        return f"{count}; {size}"


def scaled_count(count: int, height: int, width: int) -> int:
    """``count`` scaled by the frame's area relative to :data:`REFERENCE_FRAME`, rounded to the
    nearest integer (halves up) in integer arithmetic, and at least one particle when ``count`` is
    not zero: ``count`` itself on a 1024x436 frame (and on a 436x1024 one)."""
    ref = REFERENCE_FRAME[0] * REFERENCE_FRAME[1]
    n = (2 * count * height * width + ref) // (2 * ref)
    return max(n, 1) if count > 0 else 0


def scaled_size(size: int, height: int, width: int) -> int:
    """The odd size nearest to ``size`` times the ratio of the frame's diagonal to that of
    :data:`REFERENCE_FRAME` (at an even number, the odd one above), at most 2047, in integer
    arithmetic: ``size`` itself on a 1024x436 frame (and on a 436x1024 one)."""
    ref = REFERENCE_FRAME[0] ** 2 + REFERENCE_FRAME[1] ** 2
    # the nearest odd integer to x is 2 floor(x / 2) + 1; floor(x / 2) = isqrt(size^2 N // (4 ref))
    half = math.isqrt(size * size * (height * height + width * width) // (4 * ref))
    return min(2 * half + 1, 2047)


def pixel_scale(height: int, width: int) -> float:
    """The ratio of the frame's diagonal to that of :data:`REFERENCE_FRAME` (1.0 there)."""
    ref = REFERENCE_FRAME[0] ** 2 + REFERENCE_FRAME[1] ** 2
    return math.sqrt((height * height + width * width) / ref)


def frame_scaling(preset: Preset, height: int, width: int) -> FrameScaling:
    """The count and pixel sizes ``preset`` gives a frame of ``height`` x ``width`` pixels.

    With ``scale_count`` (the default) the count scales with the frame's area relative to
    1024x436 (:func:`scaled_count`), else it is ``count``; with ``scale_size`` (off by default) the
    template size scales with the frame's diagonal (:func:`scaled_size`) and so does the defocus
    radius (``pixel_scale``), else both are the paper's pixels. On a 1024x436 frame nothing
    changes.
    """
    if height < 1 or width < 1:
        raise ConfigError(f"frame of {width}x{height} pixels: needs at least one pixel")
    count = scaled_count(preset.count, height, width) if preset.scale_count else preset.count
    size = scaled_size(preset.size, height, width) if preset.scale_size else preset.size
    return FrameScaling(height=int(height), width=int(width), count=count, size=size,
                        pixel_scale=pixel_scale(height, width) if preset.scale_size else 1.0,
                        count_rule="area" if preset.scale_count else "fixed",
                        size_rule="diagonal" if preset.scale_size else "fixed",
                        preset_count=preset.count, preset_size=preset.size)


def parse_set_options(items: list[str] | tuple[str, ...]) -> dict[str, str]:
    """Turn ``["count=500", "blend=alpha"]`` into ``{"count": "500", "blend": "alpha"}``."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"${{overrides}} {item!r}: expected KEY=VALUE")
        out[key.strip()] = value
    return out


# ---------------------------------------------------------------------------------------------
# Weather-field presets
# Presets of the weather-field model: physical units, one frame rate per dataset, severity levels.
#
# A field preset is a TOML file with ``model = "field"`` (see ``presets/snow-moderate.toml``). Its
# keys are in scene units and seconds; on metric datasets (KITTI, Spring, real RGB-D data in the
# custom layout) scene units are metres, so the same preset looks alike on each of them without a
# depth scale. Keys are declared once on :class:`FieldPreset` (default, check, meaning), validated and
# resolved like the paper's presets: schema defaults < file < overrides, errors name the file, the
# key and the value.
#
# Frame rates: particles move ``velocity / frame_rate`` scene units per frame. ``frame_rate = 0``
# (the default) takes the dataset's rate, which its reader declares
# (:attr:`weathergen.datasets.Dataset.frame_rate`) and the caller passes in; any other value
# overrides it (``--set frame_rate=30``).

#: At most this many particles in one tile of the field (memory of the tile and of a frame's cull).
MAX_TILE_PARTICLES = 2_000_000


def _pair(v: tuple) -> Optional[str]:
    if len(v) != 2 or not all(math.isfinite(x) for x in v):
        return "must be two finite numbers"
    return None


def _visibility(v: float) -> Optional[str]:
    if v == 0:
        return None
    if not math.isfinite(v) or v < 10 or v > 200_000:
        return ("must be 0 (clear air) or a visibility in metres in [10, 200000] (fog: below "
                "1000, mist and haze: 1000 to 10000)")
    return None


def _airlight(value: Any) -> tuple[Any, Optional[str]]:
    """``auto`` or three integers 0-255 (a list, or text ``R,G,B``)."""
    problem = "must be auto or three integers R, G, B in [0, 255]"
    if isinstance(value, str):
        text = value.strip()
        if text == "auto":
            return "auto", None
        try:
            value = [int(part) for part in text.strip("[]").split(",")]
        except ValueError:
            return value, problem
    if not isinstance(value, (list, tuple)) or len(value) != 3 \
            or any(isinstance(c, bool) or not isinstance(c, (int, float)) for c in value) \
            or any(not float(c).is_integer() or c < 0 or c > 255 for c in value):
        return value, problem
    return tuple(int(c) for c in value), None


@dataclass(frozen=True)
class FieldPreset:
    """A weather field: particles at world positions with a density, in scene units and seconds.

    Units: lengths in scene units (metres on metric datasets), speeds in scene units per second,
    times in seconds, angles in degrees, colours 8-bit RGB.
    """

    description: str = _shared("description")
    # -- how many and how large
    density: float = _key(100.0, _number(0, 1e7),
                          "particles per cubic scene unit (0: none, for an atmosphere alone)",
                          main=True, plausible=Plausible(1e-3, 1e5, "per m³", zero=True))
    diameter: float = _key(0.005, _number(0, 1e3, lo_open=True),
                           "particle diameter, scene units", main=True,
                           plausible=PlausibleBy("templates", {
                               "flakes": Plausible(1e-4, 0.1, "m", LENGTH_SLIPS,
                                                   what="particles (flakes templates)"),
                               "dust": Plausible(1e-4, 0.1, "m", LENGTH_SLIPS,
                                                 what="particles (dust templates)"),
                               "haze": Plausible(0.1, 100, "m", what="clouds (haze templates)")},
                               Plausible(1e-4, 100, "m", LENGTH_SLIPS)))
    diameter_jitter: float = _key(0.3, _number(0, 0.9), "diameter x (1 + U[-f, f])",
                                  plausible=UNITLESS)
    templates: str = _shared("templates")
    # -- colour and opacity
    color: tuple = _shared("color")
    hue_jitter: float = _shared("hue_jitter")
    lightness_jitter: float = _shared("lightness_jitter")
    saturation_jitter: float = _shared("saturation_jitter")
    blend: str = _shared("blend")
    transparency: float = _shared("transparency", "base theta before the depth fade")
    # -- motion, per second
    fall_speed: float = _key(1.0, _number(-1e3, 1e3),
                             "speed along the world's down axis, scene units/s (< 0 rises)",
                             main=True, plausible=Plausible(-60, 60, "m/s", SPEED_SLIPS))
    speed_jitter: float = _key(0.0, _number(0, 1), "speed x (1 + U[-f, f])", plausible=UNITLESS)
    angle_jitter: float = _key(0.0, _number(0, 180),
                               "fall direction turned by Euler angles U[-a, a] degrees",
                               plausible=UNITLESS)
    wind: tuple = _key((0.0, 0.0), _pair,
                       "wind along the world's two horizontal axes, scene units/s", main=True,
                       plausible=Plausible(-60, 60, "m/s", SPEED_SLIPS))
    frame_rate: float = _key(0.0, _number(0, 1e4),
                             "frames per second; 0: the dataset's (its reader's frame_rate)",
                             plausible=Plausible(1, 1000, "fps", zero=True))
    exposure: float = _key(0.0, _number(0, 10),
                           "exposure time, s: streak length = velocity x exposure "
                           "(at most one frame interval); 0: no streak", main=True,
                           plausible=Plausible(0, 1, "s", TIME_SLIPS))
    blur_samples: int = _shared("blur_samples", "samples along a streak")
    coarse: bool = _shared("coarse")
    # -- where particles are drawn and how the lens sees them
    near: float = _key(0.1, _number(0, 1e6, lo_open=True),
                       "nearest camera depth drawn, scene units (fade-in up to 2 x near)",
                       plausible=Plausible(0.01, 100, "m", LENGTH_SLIPS))
    far: float = _key(10.0, _number(0, 1e6, lo_open=True),
                      "farthest camera depth drawn, scene units", main=True,
                      plausible=Plausible(0.1, 10_000, "m", LENGTH_SLIPS))
    fade: float = _key(0.3, _number(0, 1), "fraction of far over which particles fade out",
                       plausible=UNITLESS)
    aperture: float = _key(0.004, _number(0, 10),
                           "lens aperture diameter, scene units (0: pinhole, no defocus)",
                           plausible=Plausible(0, 0.5, "m", LENGTH_SLIPS))
    focus: float = _key(5.0, _number(0, 1e6, lo_open=True), "focus distance, scene units",
                        plausible=Plausible(0.01, 100_000, "m", LENGTH_SLIPS))
    depth_softness: float = _key(0.004, _number(0, 1e3, lo_open=True),
                                 "width of the occlusion test's transition, scene units",
                                 plausible=Plausible(1e-4, 10, "m", LENGTH_SLIPS))
    tile: float = _key(4.0, _number(0, 1e6, lo_open=True),
                       "side of the periodic tile the field repeats, scene units",
                       plausible=Plausible(0.1, 1000, "m", LENGTH_SLIPS))
    # -- the atmosphere: extinction of light with distance (see engine/weather/atmosphere.py)
    visibility: float = _key(0.0, _visibility,
                             "meteorological optical range of fog or haze (5 % contrast), metres "
                             "(scene units); 0: clear air", main=True,
                             plausible=Plausible(10, 200_000, "m", KM_SLIPS, zero=True))
    rain_rate: float = _key(0.0, _number(0, 300),
                            "rain rate, mm/h: the rain's extinction (Marshall-Palmer drops)",
                            plausible=Plausible(0, 300, "mm/h"))
    snow_rate: float = _key(0.0, _number(0, 30),
                            "snowfall rate, mm/h of liquid water: the snow's extinction",
                            plausible=Plausible(0, 30, "mm/h"))
    heterogeneity: float = _key(0.0, _number(0, 0.9),
                                "density of the air between 1 - h and 1 + h times its mean, in "
                                "banks fixed in the world; 0: uniform", plausible=UNITLESS)
    heterogeneity_scale: float = _key(20.0, _number(0.01, 1e4),
                                      "size of the largest banks of the heterogeneous air, metres "
                                      "(scene units)",
                                      plausible=Plausible(0.1, 10_000, "m", LENGTH_SLIPS))
    airlight: object = _key("auto", None, "colour of the air's in-scattered light, 8-bit RGB, or "
                                          "auto: from the frames' farthest, brightest pixels",
                            coerce=_airlight)
    sky_distance: float = _key(1000.0, _number(1, 1e7),
                               "where rays end: the distance given to the sky and to anything "
                               "farther, metres (scene units)",
                               plausible=Plausible(10, 1e6, "m", KM_SLIPS))

    # Not keys.
    name: str = field(default="custom", compare=False, metadata={"key": False})
    source: str = field(default="<defaults>", compare=False, metadata={"key": False})

    model = "field"

    @property
    def extinction(self) -> float:
        """β₀, per scene unit: fog or haze of the preset's visibility, plus its rain and
        snow (:mod:`~weathergen.engine.weather.atmosphere`); 0 for clear air."""
        return (visibility_extinction(self.visibility) + rain_extinction(self.rain_rate)
                + snow_extinction(self.snow_rate))

    @property
    def has_atmosphere(self) -> bool:
        return self.extinction > 0

    def to_dict(self) -> dict:
        """Every key with its resolved value, plus ``model``, ``name`` and ``source``."""
        return {"name": self.name, "source": self.source, "model": self.model,
                **_key_values(self, field_preset_keys())}

    def tile_count(self) -> int:
        """Particles per tile: ``round(density x tile^3)``."""
        return int(round(self.density * self.tile ** 3))

    def frame_rate_for(self, dataset_rate: Optional[float]) -> float:
        """The frame rate used on a dataset recorded at ``dataset_rate`` frames per second: the
        preset's when set, else the dataset's (ConfigError when neither is known)."""
        if self.frame_rate > 0:
            return self.frame_rate
        if dataset_rate is None:
            raise ConfigError(f"{self.source}: a weather field needs a frame rate: pass the "
                              "dataset's ${frame_rate} (its reader's frame_rate), or set the "
                              "preset's frame_rate")
        return float(dataset_rate)

    def streak_fraction(self, frame_rate: float) -> float:
        """The streak as a fraction of one frame's displacement: ``exposure x frame_rate``, at
        most 1 (a shutter cannot stay open longer than a frame)."""
        return min(1.0, self.exposure * frame_rate)

    def optics(self) -> FieldOptics:
        return FieldOptics(near=self.near, far=self.far, fade=self.fade, aperture=self.aperture,
                           focus=self.focus, depth_softness=self.depth_softness)


def field_preset_keys() -> list:
    """The schema: every field of :class:`FieldPreset` that a preset file may set."""
    return [f for f in dataclasses.fields(FieldPreset) if f.metadata.get("key", True)]


_FIELD_KEYS = {f.name: f for f in field_preset_keys()}


def build_field_preset(name: str, where: str, data: Mapping[str, Any],
                       overrides: Mapping[str, Any], base_dir: Optional[Path]) -> FieldPreset:
    """Validate a field preset's file values and overrides (see :func:`presets.load_preset`)."""
    values, templates_from = _preset_values(where, data, overrides, base_dir, _FIELD_KEYS,
                                            ignored=("name", "source"))
    preset = FieldPreset(name=name, source=where, **values)
    check_plausible(preset, _FIELD_KEYS, where, overrides)
    if not preset.far > preset.near:
        raise ConfigError(f"{where}: key 'far' = {preset.far!r}: must be greater than near "
                          f"({preset.near!r})")
    n = preset.tile_count()
    if n > MAX_TILE_PARTICLES:
        raise ConfigError(f"{where}: key 'tile' = {preset.tile!r}: density x tile^3 = {n} "
                          f"particles per tile, at most {MAX_TILE_PARTICLES}; use a smaller tile")
    if preset.density == 0:
        if not preset.has_atmosphere:
            raise ConfigError(f"{where}: key 'density' = 0: a preset without particles needs an "
                              "atmosphere (visibility, rain_rate or snow_rate)")
    elif n < 1:
        raise ConfigError(f"{where}: key 'tile' = {preset.tile!r}: density x tile^3 rounds to no "
                          "particle; use a larger tile")
    _check_template_folder(preset.templates, templates_from)
    return preset


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
    checked, templates_from = _preset_values(where, values, {}, None, _KEYS)
    preset = Preset(name=name, source=where, **checked)
    _check_consistency(preset, where)
    _check_template_folder(preset.templates, templates_from)
    return preset


def _layer_label(part: str) -> str:
    """The name a layer written as ``part`` will have: a bundled name, or a file's stem."""
    path = Path(part)
    return path.stem if part.endswith(".toml") or path.is_file() else part


def _keys_of(preset) -> Mapping[str, dataclasses.Field]:
    return _FIELD_KEYS if isinstance(preset, FieldPreset) else _KEYS


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
        lacking = [i for i, p in enumerate(plain) if key not in _keys_of(p) and key != "model"]
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
