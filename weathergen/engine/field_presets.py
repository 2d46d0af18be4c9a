"""Presets of the weather-field model: physical units, one frame rate per dataset, severity levels.

A field preset is a TOML file with ``model = "field"`` (see ``presets/snow-moderate.toml``). Its
keys are in scene units and seconds; on metric datasets (KITTI, Spring, real RGB-D data in the
custom layout) scene units are metres, so the same preset looks alike on each of them without a
depth scale. Keys are declared once on :class:`FieldPreset` (default, check, meaning), validated and
resolved like the paper's presets: schema defaults < file < overrides, errors name the file, the
key and the value.

Frame rates: particles move ``velocity / frame_rate`` scene units per frame. ``frame_rate = 0``
(the default) takes the dataset's rate from :data:`DATASET_FRAME_RATES`; any other value overrides
it (``--set frame_rate=30``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

from ..errors import ConfigError
from .particles import FieldOptics
from .presets import (BLEND_MODES, _check_template_folder, _choice, _coerce, _key, _number,
                      _resolve_templates, _rgb, _templates, parse_override)

#: Frames per second of each dataset's sequences. Sintel and Spring come from Blender open movies
#: made at 24 fps; KITTI's cameras record at 10 Hz; the bundled demo scene is defined at 24 fps.
#: Custom data has no recorded rate: 30 fps is assumed unless the preset's frame_rate says otherwise.
DATASET_FRAME_RATES = {"sintel": 24.0, "spring": 24.0, "kitti": 10.0, "demo": 24.0, "custom": 30.0}
DEFAULT_FRAME_RATE = 30.0
#: At most this many particles in one tile of the field (memory of the tile and of a frame's cull).
MAX_TILE_PARTICLES = 2_000_000


def _pair(v: tuple) -> Optional[str]:
    if len(v) != 2 or not all(math.isfinite(x) for x in v):
        return "must be two finite numbers"
    return None


@dataclass(frozen=True)
class FieldPreset:
    """A weather field: particles at world positions with a density, in scene units and seconds.

    Units: lengths in scene units (metres on metric datasets), speeds in scene units per second,
    times in seconds, angles in degrees, colours 8-bit RGB.
    """

    description: str = _key("", doc="free text shown by `weathergen presets`")
    # -- how many and how large
    density: float = _key(100.0, _number(0, 1e7, lo_open=True),
                          "particles per cubic scene unit", main=True)
    diameter: float = _key(0.005, _number(0, 1e3, lo_open=True),
                           "particle diameter, scene units", main=True)
    diameter_jitter: float = _key(0.3, _number(0, 0.9), "diameter x (1 + U[-f, f])")
    templates: str = _key("flakes", _templates,
                          "template library: flakes, dust, or a folder of grey-scale PNGs", main=True)
    # -- colour and opacity
    color: tuple = _key((255, 255, 255), _rgb, "base colour, 8-bit RGB", main=True)
    hue_jitter: float = _key(0.0, _number(0, 180), "random hue change, +- degrees")
    lightness_jitter: float = _key(0.0, _number(0, 1), "random HLS lightness change, +-")
    saturation_jitter: float = _key(0.0, _number(0, 1), "random HLS saturation change, +-")
    blend: str = _key("additive", _choice(BLEND_MODES),
                      "additive (glow) or alpha (order-independent alpha blending)", main=True)
    transparency: float = _key(0.75, _number(0, 2), "base theta before the depth fade", main=True)
    # -- motion, per second
    fall_speed: float = _key(1.0, _number(-1e3, 1e3),
                             "speed along the world's down axis, scene units/s (< 0 rises)",
                             main=True)
    speed_jitter: float = _key(0.0, _number(0, 1), "speed x (1 + U[-f, f])")
    angle_jitter: float = _key(0.0, _number(0, 180),
                               "fall direction turned by Euler angles U[-a, a] degrees")
    wind: tuple = _key((0.0, 0.0), _pair,
                       "wind along the world's two horizontal axes, scene units/s", main=True)
    frame_rate: float = _key(0.0, _number(0, 1e4),
                             "frames per second; 0: the dataset's (sintel 24, spring 24, "
                             "kitti 10, demo 24, custom 30)")
    exposure: float = _key(0.0, _number(0, 10),
                           "exposure time, s: streak length = velocity x exposure "
                           "(at most one frame interval); 0: no streak", main=True)
    blur_samples: int = _key(1, _number(1, 1000), "samples along a streak", main=True)
    # -- where particles are drawn and how the lens sees them
    near: float = _key(0.1, _number(0, 1e6, lo_open=True),
                       "nearest camera depth drawn, scene units (fade-in up to 2 x near)")
    far: float = _key(10.0, _number(0, 1e6, lo_open=True),
                      "farthest camera depth drawn, scene units", main=True)
    fade: float = _key(0.3, _number(0, 1), "fraction of far over which particles fade out")
    aperture: float = _key(0.004, _number(0, 10),
                           "lens aperture diameter, scene units (0: pinhole, no defocus)")
    focus: float = _key(5.0, _number(0, 1e6, lo_open=True), "focus distance, scene units")
    depth_softness: float = _key(0.004, _number(0, 1e3, lo_open=True),
                                 "width of the occlusion test's transition, scene units")
    tile: float = _key(4.0, _number(0, 1e6, lo_open=True),
                       "side of the periodic tile the field repeats, scene units")

    # Not keys.
    name: str = field(default="custom", compare=False, metadata={"key": False})
    source: str = field(default="<defaults>", compare=False, metadata={"key": False})

    model = "field"

    def to_dict(self) -> dict:
        """Every key with its resolved value, plus ``model``, ``name`` and ``source``."""
        out = {"name": self.name, "source": self.source, "model": self.model}
        for f in field_preset_keys():
            v = getattr(self, f.name)
            out[f.name] = list(v) if isinstance(v, tuple) else v
        return out

    def tile_count(self) -> int:
        """Particles per tile: ``round(density x tile^3)``."""
        return int(round(self.density * self.tile ** 3))

    def frame_rate_for(self, dataset: str) -> float:
        """The frame rate used for ``dataset``: the preset's when set, else the dataset's."""
        if self.frame_rate > 0:
            return self.frame_rate
        return DATASET_FRAME_RATES.get(dataset, DEFAULT_FRAME_RATE)

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
    values = {}
    templates_from = where
    for key, value in data.items():
        if isinstance(value, dict):
            raise ConfigError(f"{where}: key '{key}' is a table; preset files are flat "
                              f"(known keys: {', '.join(_FIELD_KEYS)})")
        values[key] = _coerce(where, key, value, _FIELD_KEYS)
    if base_dir is not None and "templates" in values:
        values["templates"] = _resolve_templates(values["templates"], base_dir)
    for key, value in overrides.items():
        if key in ("name", "source"):
            continue
        if isinstance(value, str):
            values[key] = parse_override(key, value, keys=_FIELD_KEYS)
        else:
            values[key] = _coerce("override", key, value, _FIELD_KEYS)
        if key == "templates":
            templates_from = "${overrides}" if isinstance(value, str) else "override"
    preset = FieldPreset(name=name, source=where, **values)
    if not preset.far > preset.near:
        raise ConfigError(f"{where}: key 'far' = {preset.far!r}: must be greater than near "
                          f"({preset.near!r})")
    n = preset.tile_count()
    if n > MAX_TILE_PARTICLES:
        raise ConfigError(f"{where}: key 'tile' = {preset.tile!r}: density x tile^3 = {n} "
                          f"particles per tile, at most {MAX_TILE_PARTICLES}; use a smaller tile")
    if n < 1:
        raise ConfigError(f"{where}: key 'tile' = {preset.tile!r}: density x tile^3 rounds to no "
                          "particle; use a larger tile")
    _check_template_folder(preset.templates, templates_from)
    return preset
