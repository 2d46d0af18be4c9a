"""The render settings of a particle record: how its particles are drawn, declared once.

A :class:`RenderSettings` record travels with the particles (``Particles.settings``): sampling
makes it from the preset (:meth:`RenderSettings.from_preset`), the renderer reads it, the particle
file stores it once (:meth:`RenderSettings.to_arrays`, one 0-d array per field) and reading the
file gives it back (:meth:`RenderSettings.from_arrays`).

The preset keys it comes from are ``blend``, ``motion_blur``, ``blur_length``, ``blur_samples``,
``defocus_brighten``, ``coarse`` and ``templates``; all but ``templates`` change only how stored
particles look, so they may change when stored particles are rendered again
(:data:`APPEARANCE_KEYS`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional

import numpy as np

from ...errors import ConfigError, FormatError
from ..weather.presets import BLEND_MODES, Preset
from ..weather.templates import TemplateLibrary

#: Preset keys that only change how stored particles look, so they may change on re-rendering.
APPEARANCE_KEYS = ("blend", "motion_blur", "blur_length", "blur_samples", "defocus_brighten",
                   "coarse")
#: The fields of :class:`RenderSettings` that :data:`APPEARANCE_KEYS` set.
APPEARANCE_FIELDS = ("blend", "blur_length", "blur_samples", "defocus_brighten", "coarse")
#: Fields a particle file holds only when they differ from their default (files written before
#: they existed read as the default, and files of the default keep their bytes).
OPTIONAL_FIELDS = ("coarse", "blur_blend", "depth_shift", "stamp_style")
#: How an α-blended record's blur samples are blended: all at once, or one after another.
BLUR_BLENDS = ("sum", "sequential")
#: How a record's stamps are made from its templates: weathergen's, or as the research code does.
STAMP_STYLES = ("smooth", "research")


@dataclass(frozen=True)
class RenderSettings:
    """How a record's particles are drawn.

    blend: ``additive`` (glow) or ``alpha``; blur_length: the motion-blur streak as a fraction of
    the frame-to-frame motion (0: none); blur_samples: samples K per blurred particle (1: none);
    defocus_brighten: brighten the disc-blurred alpha b to min(1, (2 b)^(1/3)); templates: the
    template library's name (``flakes``, ``dust`` or a folder); templates_digest: its digest ("" for
    any), so that particles are never drawn with other templates than they were sampled with;
    coarse: stamps of at least ``COARSE_SIDE`` pixels may be drawn on a coarser grid (false:
    every pixel exactly); blur_blend: how an α-blended record's K blur samples are blended,
    ``sum``: all at once, ``I (1 − ΣA) + ΣC`` (weathergen's), ``sequential``: one after another
    in their order along the streak, ``I_k = clamp(I_{k−1} (1 − A_k) + C_k, 0, 1)`` (the
    research code's; what ``compat="reference"`` draws, see :meth:`for_compat`); depth_shift:
    where the scene depth a particle is tested against is read, this many pixels up and left of
    each pixel, bilinearly (0: at the pixel, weathergen's; 0.5: the research code's);
    stamp_style: ``smooth`` (weathergen's: the footprint as sampled, a defocused stamp softened
    by the box of :func:`~weathergen.engine.rendering.stamps.soft_box`) or ``research`` (what
    ``compat="reference"`` draws: the footprint of the research code's whole-pixel flake
    window, no softening, the record's own blur samples; see docs/render.md, "The look of the
    paper's presets").
    """

    blend: str = "additive"
    blur_length: float = 0.0
    blur_samples: int = 1
    defocus_brighten: bool = True
    templates: str = "flakes"
    templates_digest: str = ""
    coarse: bool = True
    blur_blend: str = "sum"
    depth_shift: float = 0.0
    stamp_style: str = "smooth"

    def __post_init__(self):
        if self.blur_blend not in BLUR_BLENDS:
            raise ConfigError(f"blur_blend must be {' or '.join(BLUR_BLENDS)}; "
                              f"got {self.blur_blend!r}")
        if not 0 <= self.depth_shift <= 1:
            raise ConfigError(f"depth_shift must be in [0, 1]; got {self.depth_shift!r}")
        if self.stamp_style not in STAMP_STYLES:
            raise ConfigError(f"stamp_style must be {' or '.join(STAMP_STYLES)}; "
                              f"got {self.stamp_style!r}")

    @classmethod
    def from_preset(cls, preset: Preset, library: Optional[TemplateLibrary] = None) -> "RenderSettings":
        """The settings a preset asks for (motion blur off: one sample, no streak); the library,
        when given, names the templates and their digest."""
        return cls(blend=preset.blend, blur_length=preset.effective_blur_length,
                   blur_samples=preset.blur_sample_count, defocus_brighten=preset.defocus_brighten,
                   templates=library.name if library is not None else preset.templates,
                   templates_digest=library.digest if library is not None else "",
                   coarse=preset.coarse)

    @property
    def motion_blurred(self) -> bool:
        """More than one blur sample along a streak of some length."""
        return self.blur_samples > 1 and self.blur_length > 0

    @property
    def blends_in_order(self) -> bool:
        """Whether the record's blur samples are blended one after another: ``sequential``,
        α-blended, motion-blurred."""
        return self.blur_blend == "sequential" and self.blend == "alpha" and self.motion_blurred

    def for_compat(self, compat: str) -> "RenderSettings":
        """The settings drawn under ``compat``: ``reference`` blends the blur samples of an
        α-blended, motion-blurred record one after another, reads the scene depth half a
        pixel up and left and makes its stamps as the research code does (``sequential``,
        ``depth_shift`` 0.5, ``research``); ``paper`` all at once at the pixel, weathergen's
        stamps (``sum``, 0, ``smooth``). The other fields are kept."""
        reference = compat == "reference"
        ordered = reference and self.blend == "alpha" and self.motion_blurred
        return self.replace(blur_blend="sequential" if ordered else "sum",
                            depth_shift=0.5 if reference else 0.0,
                            stamp_style="research" if reference else "smooth")

    def appearance(self) -> dict:
        """The fields that may change when stored particles are rendered again."""
        return {name: getattr(self, name) for name in APPEARANCE_FIELDS}

    def replace(self, **changes) -> "RenderSettings":
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """One 0-d array per field, in declaration order (the particle file's entries); the
        :data:`OPTIONAL_FIELDS` only where they differ from their default."""
        defaults = RenderSettings()
        return {name: np.array(value) for name, value in self.to_dict().items()
                if name not in OPTIONAL_FIELDS or value != getattr(defaults, name)}

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray], path: str | Path) -> "RenderSettings":
        """The settings stored by :meth:`to_arrays`; FormatError names ``path`` and the entry."""
        values = {}
        for f in dataclasses.fields(cls):
            if f.name not in arrays and f.name in OPTIONAL_FIELDS:
                continue
            if f.name not in arrays:
                raise FormatError(path, f"missing field '{f.name}'")
            values[f.name] = type(f.default)(arrays[f.name].item())
        if values["blend"] not in BLEND_MODES:
            raise FormatError(path, f"unknown blend mode {values['blend']!r}")
        if values.get("blur_blend", "sum") not in BLUR_BLENDS:     # (before __post_init__'s)
            raise FormatError(path, f"unknown blur_blend {values['blur_blend']!r} (expected "
                                    f"{' or '.join(BLUR_BLENDS)})")
        if not 0 <= values.get("depth_shift", 0.0) <= 1:
            raise FormatError(path, f"depth_shift must be in [0, 1], got {values['depth_shift']}")
        if values.get("stamp_style", "smooth") not in STAMP_STYLES:
            raise FormatError(path, f"unknown stamp_style {values['stamp_style']!r} (expected "
                                    f"{' or '.join(STAMP_STYLES)})")
        return cls(**values)
