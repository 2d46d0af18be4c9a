"""The paper's presets: :class:`Preset` (every key declared once), a preset file's values checked
against a schema (:func:`preset_values`, :func:`parse_override`), and a paper preset's count and
sizes on another frame size (:func:`frame_scaling`)."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

from ...errors import ConfigError, WeatherGenError
from .templates import BUILTIN_TEMPLATE_KINDS, load_templates
from .preset_schema import (TRANSPARENCY_MODES, Plausible, choice_check, count_check,
                            interval_check, number_check, odd_size_check, preset_key, shared_key)

@dataclass(frozen=True)
class Preset:
    """One weather configuration, fully resolved and validated. Every field is a preset key.

    Units: lengths and motions in scene units (those of the frame pair's depth), sizes in pixels,
    angles in degrees, colours as 8-bit RGB.
    """

    description: str = shared_key("description")
    # -- particle base properties
    count: int = preset_key(3000, count_check, "particles per frame pair of 1024x436 pixels; other frame "
                                               "sizes scale it by their area (see scale_count)", main=True)
    size: int = preset_key(71, odd_size_check, "template side in pixels at depth <= 1/depth_decay (odd)",
                           main=True)
    scale_count: bool = preset_key(True, None, "scale count with the frame's area relative to 1024x436, "
                                               "keeping particles per pixel area (false: count on every "
                                               "frame; --set count=N sets it false)")
    scale_size: bool = preset_key(False, None, "scale size and the defocus radius with the frame's "
                                               "diagonal relative to 1024x436 (with scale_count false: "
                                               "the frame as a resized 1024x436 one; --set size=N sets "
                                               "it false)")
    depth_decay: float = preset_key(9.0, number_check(0, 1e6, lo_open=True),
                                    "size scales by min(1, 1/(depth * depth_decay))", main=True)
    templates: str = shared_key("templates")
    # -- colour
    color: tuple = shared_key("color")
    hue_jitter: float = shared_key("hue_jitter")
    lightness_jitter: float = shared_key("lightness_jitter")
    saturation_jitter: float = shared_key("saturation_jitter")
    blend: str = shared_key("blend")
    transparency: float = shared_key("transparency",
                                     "theta = this x depth hat (the hat peaks at 0.73), or this value "
                                     "itself when transparency_mode is constant")
    transparency_mode: str = preset_key("depth", choice_check(TRANSPARENCY_MODES),
                                        "depth: hat over depth; constant: theta for every particle")
    # -- motion
    motion_y: float = preset_key(0.2, number_check(-1e3, 1e3),
                                 "frame-to-frame fall distance, > 0 falls down, < 0 rises", main=True)
    motion_scale_jitter: float = preset_key(0.0, number_check(0, 1),
                                            "motion length scaled by 1 + U[-f, f]")
    motion_angle_jitter: float = preset_key(0.0, number_check(0, 180),
                                            "motion direction turned by Euler angles U[-a, a] degrees")
    # -- motion blur
    motion_blur: bool = preset_key(False, None, "render K samples along the 3D motion", main=True)
    blur_length: float = preset_key(0.0, number_check(0, 10),
                                    "blur streak as a fraction of the frame-to-frame motion", main=True)
    blur_samples: int = shared_key("blur_samples", "samples K per blurred particle")
    # -- out-of-focus blur
    defocus: bool = preset_key(True, None, "disc blur for particles near the focal distance")
    defocus_brighten: bool = preset_key(True, None,
                                        "brighten the disc-blurred alpha b to min(1, (2b)^(1/3))")
    coarse: bool = shared_key("coarse")
    # -- where particles are sampled, camera-1 coordinates
    volume_x: tuple = preset_key((-5.0, 5.0), interval_check, "sampling box x range, camera 1")
    volume_y: tuple = preset_key((-5.0, 5.0), interval_check, "sampling box y range, camera 1")
    volume_z: tuple = preset_key((0.0, 3.0), interval_check, "sampling box z (depth) range, camera 1")

    # Not keys: where the preset came from (for messages and manifests).
    name: str = field(default="custom", compare=False, metadata={"key": False})
    source: str = field(default="<defaults>", compare=False, metadata={"key": False})

    def to_dict(self) -> dict:
        """Every key with its resolved value, plus ``name`` and ``source`` (for manifests)."""
        return {"name": self.name, "source": self.source, **key_values(self, preset_keys())}

    @property
    def blur_sample_count(self) -> int:
        """The number of samples actually rendered per particle (1 when motion blur is off)."""
        return self.blur_samples if self.motion_blur else 1

    @property
    def effective_blur_length(self) -> float:
        return self.blur_length if self.motion_blur else 0.0


def key_values(preset, keys: list[dataclasses.Field]) -> dict:
    """The values of a preset's ``keys``, tuples as lists (as TOML and JSON write them)."""
    out = {}
    for f in keys:
        v = getattr(preset, f.name)
        out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


def preset_keys() -> list[dataclasses.Field]:
    """The schema: every field of :class:`Preset` that a preset file may set."""
    return [f for f in dataclasses.fields(Preset) if f.metadata.get("key", True)]


PAPER_KEYS = {f.name: f for f in preset_keys()}


def _coerce(where: str, key: str, value: Any, keys: Optional[Mapping] = None) -> Any:
    """Type-check one value against the schema (``keys``, default :class:`Preset`'s); return it in
    its canonical Python type."""
    keys = PAPER_KEYS if keys is None else keys
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
    keys = PAPER_KEYS if keys is None else keys
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


def preset_values(where: str, data: Mapping[str, Any], overrides: Mapping[str, Any],
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


def check_template_folder(value: str, where: str) -> None:
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


def check_consistency(p: Preset, where: str) -> None:
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


