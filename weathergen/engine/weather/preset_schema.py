"""The preset key schema, with which both models' presets declare their keys: a key declared once
(:func:`preset_key`: default, check, meaning, plausible range), the checks of a value, the keys
both models share (:data:`SHARED_KEYS`), the warning for an implausible value."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Optional

from ...errors import ConfigError
from .templates import BUILTIN_TEMPLATE_KINDS

BLEND_MODES = ("additive", "alpha")
TRANSPARENCY_MODES = ("depth", "constant")


# ---------------------------------------------------------------------------------------------
# Checks: each returns an error text (what the value must be) or None when the value is fine.

def number_check(lo: float = -math.inf, hi: float = math.inf, *, lo_open: bool = False
                 ) -> Callable[[Any], Optional[str]]:
    def check(v):
        if not math.isfinite(v):
            return "must be a finite number"
        if v < lo or (lo_open and v == lo) or v > hi:
            left = "(" if lo_open else "["
            return f"must lie in {left}{lo:g}, {hi:g}]"
        return None
    return check


def odd_size_check(v: int) -> Optional[str]:
    if v < 1 or v % 2 == 0:
        return "must be an odd number of pixels >= 1 (templates are centred on a pixel)"
    if v > 2047:
        return "must be at most 2047 pixels"
    return None


def count_check(v: int) -> Optional[str]:
    return "must be a count >= 0" if v < 0 else ("must be at most 1000000" if v > 1_000_000 else None)


def rgb_check(v: tuple) -> Optional[str]:
    if len(v) != 3:
        return "must be three integers (R, G, B)"
    if any(c < 0 or c > 255 for c in v):
        return "must be three integers in [0, 255]"
    return None


def interval_check(v: tuple) -> Optional[str]:
    if len(v) != 2 or not all(math.isfinite(x) for x in v):
        return "must be two finite numbers [min, max]"
    if not v[0] < v[1]:
        return "must satisfy min < max"
    return None


def choice_check(options: tuple[str, ...]) -> Callable[[str], Optional[str]]:
    return lambda v: None if v in options else f"must be one of {', '.join(options)}"


def templates_check(v: str) -> Optional[str]:
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


def preset_key(default, check=None, doc: str = "", main: bool = False, plausible=None, coerce=None):
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
    "templates": ("flakes", templates_check,
                  "template library: flakes, dust, haze, or a folder of grey-scale PNGs", True, None),
    "color": ((255, 255, 255), rgb_check, "base colour, 8-bit RGB", True, UNITLESS),
    "hue_jitter": (0.0, number_check(0, 180), "random hue change, +- degrees", False, UNITLESS),
    "lightness_jitter": (0.0, number_check(0, 1), "random HLS lightness change, +-", False, UNITLESS),
    "saturation_jitter": (0.0, number_check(0, 1), "random HLS saturation change, +-", False, UNITLESS),
    "blend": ("additive", choice_check(BLEND_MODES),
              "additive (glow) or alpha (order-independent alpha blending)", True, None),
    "transparency": (0.75, number_check(0, 2), "", True, UNITLESS),
    "blur_samples": (1, number_check(1, 1000), "", True, UNITLESS),
    "coarse": (True, None, "draw stamps of at least 128 px (fog, large dust) on a coarser grid "
                           "and upsample them across depth edges (fast, within the tolerance of "
                           "docs/engine.md); false: every pixel exactly", False, None),
}


def shared_key(name: str, doc: str = ""):
    """A key of :data:`SHARED_KEYS` (``doc``: the model's own description, where it has one)."""
    default, check, text, main, plausible = SHARED_KEYS[name]
    return preset_key(default, check, doc or text, main, plausible)


