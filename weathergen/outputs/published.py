"""The paper's published weather read as a weather folder: what ``evaluate`` needs from a set of
the research code's particle files (:mod:`weathergen.io.published_weather`).

A published ``_npz`` set holds particles, no frames of weathergen's: :class:`PublishedWeatherSet`
draws each pair's particles into the clean pair (:func:`~weathergen.engine.render_pair` of
:func:`~weathergen.engine.sampling.published.published_particles`, with a preset's render settings) and
gives those frames rounded to 8 bits, as ``render`` would write them, so that ``evaluate`` of a
set measures what ``render --particles SET --compat reference`` followed by ``evaluate``
measures. It offers the
attributes and methods of :class:`~weathergen.outputs.WeatherFolder` that evaluation reads.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import torch

from ..datasets import Dataset
from ..engine import Preset, render_pair
from ..engine.sampling.published import published_particles
from ..errors import DatasetError
from ..framepair import FramePair, PairId
from ..io.images import to_uint8
from ..io.published_weather import published_file, read_published_weather


@dataclass
class PublishedWeatherSet:
    """A published set opened for evaluation against ``dataset`` (its clean pairs).

    Attributes: root; preset and preset_name (how the particles are drawn); dataset; pairs (the
    dataset's pairs the set has a file for, sorted); pass_name (a label: ``<preset>_published``).
    """

    root: Path
    preset: Preset
    preset_name: str
    dataset: Dataset
    pairs: list
    pass_name: str = ""
    _cache: dict = field(default_factory=dict, repr=False)

    @classmethod
    def open(cls, root: str | Path, dataset: Dataset, preset: Preset,
             preset_name: str) -> "PublishedWeatherSet":
        """The set at ``root``: the pairs of ``dataset`` that have a file there.

        Raises:
            DatasetError: no selected pair has a file in the set.
        """
        root = Path(root)
        pairs = sorted(ref.id for ref in dataset.pairs()
                       if published_file(root, ref.id.scene, ref.id.frame).is_file())
        if not pairs:
            raise DatasetError(f"{root}: holds no particle file for a selected pair of "
                               f"{dataset.root} (expected SCENE/frame_NNNN.npz)")
        return cls(root, preset, preset_name, dataset, pairs, f"{preset_name}_published")

    def _pair(self, pair_id: PairId) -> FramePair:
        if pair_id not in self._cache:
            refs = {(r.id.split, r.id.scene, r.id.frame): r for r in self.dataset.pairs()}
            self._cache.clear()                  # one pair at a time
            self._cache[pair_id] = self.dataset.load(refs[(pair_id.split, pair_id.scene,
                                                           pair_id.frame)])
        return self._cache[pair_id]

    def particles(self, pair_id: PairId):
        """The pair's particles, mapped into its clean pair, drawn as under ``--compat
        reference`` (α-blended motion blur blended sample by sample, as the research code)."""
        weather = read_published_weather(published_file(self.root, pair_id.scene, pair_id.frame))
        return published_particles(weather, self._pair(pair_id), self.preset).for_compat("reference")

    def frames(self, pair_id: PairId) -> tuple[torch.Tensor, torch.Tensor]:
        """The weather frames of a pair, drawn and rounded to 8 bits as ``render`` writes them.
        Shape: two (3, H, W) float32 in [0, 1]."""
        with torch.no_grad():
            out = render_pair(self._pair(pair_id), self.particles(pair_id))
        return tuple(torch.from_numpy(to_uint8(img[0].permute(1, 2, 0).numpy())).permute(2, 0, 1)
                     .float().div(255).contiguous() for img in (out.image1, out.image2))

    def clean_dataset(self, dataset: Optional[str] = None, root: Optional[str] = None,
                      pass_: Optional[str] = None) -> Dataset:
        """The clean dataset the set was opened with (its options were given when opening)."""
        return self.dataset
