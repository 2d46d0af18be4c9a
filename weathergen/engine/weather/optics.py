"""How a weather-field record looks in each frame: the optics it carries (near, far, fade, lens).

A plain frozen record with no dependencies, so that presets (which make it) and particle records
(which carry it) can both import it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class FieldOptics:
    """How a field-sampled record looks in each frame (see :mod:`weathergen.engine.rendering.tracks`).

    Lengths in scene units: ``near``/``far`` bound the camera depths at which particles are drawn;
    ``fade`` is the fraction of ``far`` over which they fade out before it (and they fade in over
    ``[near, 2 near]``); ``aperture`` is the lens's aperture diameter (0: pinhole, no defocus),
    focused at ``focus``; ``depth_softness`` is the width of the occlusion test's transition
    (visibility ``sigmoid((D - d) / depth_softness)``), large for fog so that a slanted wall fades
    it instead of cutting it.
    """

    near: float
    far: float
    fade: float = 0.2
    aperture: float = 0.0
    focus: float = 1.0
    depth_softness: float = 0.004

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "FieldOptics":
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"unknown optics keys {unknown}")
        return cls(**{k: float(v) for k, v in data.items()})
