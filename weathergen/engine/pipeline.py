"""The engine in one call: any preset's weather sampled for a frame pair and rendered into it.

::

    from weathergen.engine import Weather
    out = Weather("fog-moderate", seed=0).render(pair)     # out.image1, out.image2, out.opacity1, ...

A :class:`Weather` takes every kind of preset — the paper's (``snow``), a weather field
(``snow-moderate``), an atmosphere alone (``fog-moderate``) and combinations
(``rain-heavy+fog-light``) — and reads what the model needs from the pair: its dataset's frame
rate (:attr:`~weathergen.framepair.FramePair.frame_rate`) and, for an ``auto`` airlight, the
pair's own. Sampling stays apart from rendering (:meth:`Weather.sample`), so the record can be
saved, optimised or drawn again with :func:`~weathergen.engine.rendering.renderer.render_pair`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Union

from ..framepair import FramePair
from .records.layered import LayeredParticles
from .records.particles import Particles
from .rendering.composite import RenderOutput
from .rendering.renderer import render_pair
from .sampling.field import sample_weather
from .weather.presets import CombinedPreset, FieldPreset, Preset, load_preset

AnyPreset = Union[Preset, FieldPreset, CombinedPreset]


@dataclass(frozen=True)
class Weather:
    """A preset and the seed of its random draws, ready to be sampled for or rendered into pairs.

    ``preset``: a bundled preset's name, a preset file, ``a+b`` for combined weather, or a loaded
    preset; ``overrides`` as for :func:`~weathergen.engine.weather.presets.load_preset` (only with a
    name or a file). ``seed``: for a weather field, the field's, so that the pairs of one scene
    rendered with one :class:`Weather` show the same weather in their shared frames; for a paper
    preset, the draw of each pair.
    """

    preset: Union[str, Path, AnyPreset]
    seed: int = 0
    overrides: Optional[Mapping[str, Any]] = field(default=None, compare=False)

    def __post_init__(self):
        if isinstance(self.preset, (str, Path)):
            object.__setattr__(self, "preset", load_preset(self.preset, self.overrides))

    def sample(self, pair: FramePair, *, device=None) -> Union[Particles, LayeredParticles]:
        """The pair's particles (:func:`~weathergen.engine.sampling.field.sample_weather`), with the
        pair's frame rate and airlight."""
        return sample_weather(pair, self.preset, self.seed, device=device)

    def render(self, pair: FramePair, *, device=None, **options) -> RenderOutput:
        """The pair with this weather drawn in; ``options`` go to :func:`render_pair`.
        Shape: returns images (1, 3, H, W) and opacities (1, 1, H, W)."""
        return render_pair(pair, self.sample(pair, device=device), device=device, **options)
