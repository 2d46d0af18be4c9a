"""The weather-field model's presets (:class:`FieldPreset`, :func:`build_field_preset`):
physical units, one frame rate per dataset, severity levels.

A field preset is a TOML file with ``model = "field"`` (see ``presets/snow-moderate.toml``). Its
keys are in scene units and seconds; on metric datasets (KITTI, Spring, real RGB-D data in the
custom layout) scene units are metres, so the same preset looks alike on each of them without a
depth scale. Keys are declared once on :class:`FieldPreset` (default, check, meaning), validated and
resolved like the paper's presets: schema defaults < file < overrides, errors name the file, the
key and the value.

Frame rates: particles move ``velocity / frame_rate`` scene units per frame. ``frame_rate = 0``
(the default) takes the dataset's rate, which its reader declares
(:attr:`weathergen.datasets.Dataset.frame_rate`) and the caller passes in; any other value
overrides it (``--set frame_rate=30``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional

from ...errors import ConfigError
from .atmosphere import rain_extinction, snow_extinction, visibility_extinction
from .optics import FieldOptics
from .paper_presets import check_template_folder, key_values, preset_values
from .preset_schema import (KM_SLIPS, LENGTH_SLIPS, SPEED_SLIPS, TIME_SLIPS, UNITLESS, Plausible,
                            PlausibleBy, check_plausible, number_check, preset_key, shared_key)

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

    description: str = shared_key("description")
    # -- how many and how large
    density: float = preset_key(100.0, number_check(0, 1e7),
                                "particles per cubic scene unit (0: none, for an atmosphere alone)",
                                main=True, plausible=Plausible(1e-3, 1e5, "per m³", zero=True))
    diameter: float = preset_key(0.005, number_check(0, 1e3, lo_open=True),
                                 "particle diameter, scene units", main=True,
                                 plausible=PlausibleBy("templates", {
                                     "flakes": Plausible(1e-4, 0.1, "m", LENGTH_SLIPS,
                                                         what="particles (flakes templates)"),
                                     "dust": Plausible(1e-4, 0.1, "m", LENGTH_SLIPS,
                                                       what="particles (dust templates)"),
                                     "haze": Plausible(0.1, 100, "m", what="clouds (haze templates)")},
                                     Plausible(1e-4, 100, "m", LENGTH_SLIPS)))
    diameter_jitter: float = preset_key(0.3, number_check(0, 0.9), "diameter x (1 + U[-f, f])",
                                        plausible=UNITLESS)
    templates: str = shared_key("templates")
    # -- colour and opacity
    color: tuple = shared_key("color")
    hue_jitter: float = shared_key("hue_jitter")
    lightness_jitter: float = shared_key("lightness_jitter")
    saturation_jitter: float = shared_key("saturation_jitter")
    blend: str = shared_key("blend")
    transparency: float = shared_key("transparency", "base theta before the depth fade")
    # -- motion, per second
    fall_speed: float = preset_key(1.0, number_check(-1e3, 1e3),
                                   "speed along the world's down axis, scene units/s (< 0 rises)",
                                   main=True, plausible=Plausible(-60, 60, "m/s", SPEED_SLIPS))
    speed_jitter: float = preset_key(0.0, number_check(0, 1), "speed x (1 + U[-f, f])", plausible=UNITLESS)
    angle_jitter: float = preset_key(0.0, number_check(0, 180),
                                     "fall direction turned by Euler angles U[-a, a] degrees",
                                     plausible=UNITLESS)
    wind: tuple = preset_key((0.0, 0.0), _pair,
                             "wind along the world's two horizontal axes, scene units/s", main=True,
                             plausible=Plausible(-60, 60, "m/s", SPEED_SLIPS))
    frame_rate: float = preset_key(0.0, number_check(0, 1e4),
                                   "frames per second; 0: the dataset's (its reader's frame_rate)",
                                   plausible=Plausible(1, 1000, "fps", zero=True))
    exposure: float = preset_key(0.0, number_check(0, 10),
                                 "exposure time, s: streak length = velocity x exposure "
                                 "(at most one frame interval); 0: no streak", main=True,
                                 plausible=Plausible(0, 1, "s", TIME_SLIPS))
    blur_samples: int = shared_key("blur_samples", "samples along a streak")
    coarse: bool = shared_key("coarse")
    # -- where particles are drawn and how the lens sees them
    near: float = preset_key(0.1, number_check(0, 1e6, lo_open=True),
                             "nearest camera depth drawn, scene units (fade-in up to 2 x near)",
                             plausible=Plausible(0.01, 100, "m", LENGTH_SLIPS))
    far: float = preset_key(10.0, number_check(0, 1e6, lo_open=True),
                            "farthest camera depth drawn, scene units", main=True,
                            plausible=Plausible(0.1, 10_000, "m", LENGTH_SLIPS))
    fade: float = preset_key(0.3, number_check(0, 1), "fraction of far over which particles fade out",
                             plausible=UNITLESS)
    aperture: float = preset_key(0.004, number_check(0, 10),
                                 "lens aperture diameter, scene units (0: pinhole, no defocus)",
                                 plausible=Plausible(0, 0.5, "m", LENGTH_SLIPS))
    focus: float = preset_key(5.0, number_check(0, 1e6, lo_open=True), "focus distance, scene units",
                              plausible=Plausible(0.01, 100_000, "m", LENGTH_SLIPS))
    depth_softness: float = preset_key(0.004, number_check(0, 1e3, lo_open=True),
                                       "width of the occlusion test's transition, scene units",
                                       plausible=Plausible(1e-4, 10, "m", LENGTH_SLIPS))
    tile: float = preset_key(4.0, number_check(0, 1e6, lo_open=True),
                             "side of the periodic tile the field repeats, scene units",
                             plausible=Plausible(0.1, 1000, "m", LENGTH_SLIPS))
    # -- the atmosphere: extinction of light with distance (see engine/weather/atmosphere.py)
    visibility: float = preset_key(0.0, _visibility,
                                   "meteorological optical range of fog or haze (5 % contrast), metres "
                                   "(scene units); 0: clear air", main=True,
                                   plausible=Plausible(10, 200_000, "m", KM_SLIPS, zero=True))
    rain_rate: float = preset_key(0.0, number_check(0, 300),
                                  "rain rate, mm/h: the rain's extinction (Marshall-Palmer drops)",
                                  plausible=Plausible(0, 300, "mm/h"))
    snow_rate: float = preset_key(0.0, number_check(0, 30),
                                  "snowfall rate, mm/h of liquid water: the snow's extinction",
                                  plausible=Plausible(0, 30, "mm/h"))
    heterogeneity: float = preset_key(0.0, number_check(0, 0.9),
                                      "density of the air between 1 - h and 1 + h times its mean, in "
                                      "banks fixed in the world; 0: uniform", plausible=UNITLESS)
    heterogeneity_scale: float = preset_key(20.0, number_check(0.01, 1e4),
                                            "size of the largest banks of the heterogeneous air, metres "
                                            "(scene units)",
                                            plausible=Plausible(0.1, 10_000, "m", LENGTH_SLIPS))
    airlight: object = preset_key("auto", None, "colour of the air's in-scattered light, 8-bit RGB, or "
                                                "auto: from the frames' farthest, brightest pixels",
                                  coerce=_airlight)
    sky_distance: float = preset_key(1000.0, number_check(1, 1e7),
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
                **key_values(self, field_preset_keys())}

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


FIELD_KEYS = {f.name: f for f in field_preset_keys()}


def build_field_preset(name: str, where: str, data: Mapping[str, Any],
                       overrides: Mapping[str, Any], base_dir: Optional[Path]) -> FieldPreset:
    """Validate a field preset's file values and overrides (see :func:`presets.load_preset`)."""
    values, templates_from = preset_values(where, data, overrides, base_dir, FIELD_KEYS,
                                           ignored=("name", "source"))
    preset = FieldPreset(name=name, source=where, **values)
    check_plausible(preset, FIELD_KEYS, where, overrides)
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
    check_template_folder(preset.templates, templates_from)
    return preset


