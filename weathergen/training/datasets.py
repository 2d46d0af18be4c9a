"""Dataset readers as PyTorch datasets: frame pairs for a training loop, in batches.

Any reader of :mod:`weathergen.datasets` (Sintel, KITTI, Spring, custom, demo) becomes a
``torch.utils.data.Dataset`` whose items are :class:`PairSample` records: the
:class:`~weathergen.framepair.FramePair` exactly as the reader loads it (frames, depth, cameras,
flow and validity where the dataset has them), its index in the dataset and the epoch it was
drawn for. :func:`collate_pairs` stacks samples of equal size into a :class:`PairSampleBatch`::

    from torch.utils.data import DataLoader
    from weathergen.datasets import open_dataset
    from weathergen.training import PairDataset, WeatherAugment, collate_pairs

    data = PairDataset(open_dataset("sintel", "/data/MPI-Sintel", pass_="final"),
                       transform=WeatherAugment(["snow"], p=0.5, seed=1234))
    loader = DataLoader(data, batch_size=6, shuffle=True, num_workers=4,
                        collate_fn=collate_pairs)
    for epoch in range(epochs):
        data.set_epoch(epoch)            # new weather every epoch
        for batch in loader:
            batch.pairs.image1, batch.pairs.flow, ...   # (B, 3, H, W), (B, 2, H, W)

Random draws of the transforms are keyed by ``(seed, epoch, index)``, so they do not depend on
the number of workers or on the order in which workers finish. :meth:`PairDataset.set_epoch`
reaches the workers because the ``DataLoader`` copies the dataset into fresh worker processes at
the start of every epoch; with ``persistent_workers=True`` the workers keep their old copy, so
wrap the sampler in :class:`EpochSampler` instead, whose ``(epoch, index)`` keys carry the epoch
to the workers with every item.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterator, Optional, Sequence

import torch
from torch.utils.data import Dataset as TorchDataset
from torch.utils.data import Sampler

from ..datasets import Dataset
from ..errors import ConfigError
from ..framepair import FramePair, FramePairBatch


@dataclass
class PairSample:
    """One training sample: a frame pair and the key its random draws are made from.

    Attributes:
        pair: the frame pair (after any transforms applied so far).
        index: the pair's position in the :class:`PairDataset`.
        epoch: the epoch the sample was drawn for.
        world_up: the dataset's world-up setting (which way weather falls), see
            :func:`weathergen.engine.sampling.pair.world_down`.
        weather: what the weather transform did (:class:`~weathergen.training.augment.WeatherDraw`),
            ``None`` before it ran.
        particles: the rendered particle record where the transform was asked to keep it.
    """

    pair: FramePair
    index: int
    epoch: int = 0
    world_up: str = "auto"
    weather: Any = None
    particles: Any = None


@dataclass
class PairSampleBatch:
    """``B`` samples of equal size: the stacked pairs and, per sample, its draw key.

    Shape: ``pairs`` as :class:`~weathergen.framepair.FramePairBatch` (images ``(B, 3, H, W)``,
    flow ``(B, 2, H, W)``, ...); ``indices`` and ``epochs`` ``(B,)`` int64.
    """

    pairs: FramePairBatch
    indices: torch.Tensor
    epochs: torch.Tensor
    world_up: list = field(default_factory=list)
    weather: list = field(default_factory=list)
    particles: list = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.indices.numel())

    def to(self, device) -> "PairSampleBatch":
        """A copy with the pairs' tensors on ``device`` (keys stay on the CPU)."""
        return replace(self, pairs=batch_to(self.pairs, device))

    def sample(self, k: int) -> PairSample:
        """The ``k``-th sample, its tensors views into the batch."""
        return PairSample(pair=pair_of(self.pairs, k), index=int(self.indices[k]),
                          epoch=int(self.epochs[k]), world_up=self.world_up[k],
                          weather=self.weather[k], particles=self.particles[k])


_BATCH_TENSORS = ("image1", "image2", "depth1", "depth2", "intrinsics", "cam2_from_cam1",
                  "cam1_from_world", "cam2_from_world", "flow", "flow_valid",
                  "depth_provenance1", "depth_provenance2")


def batch_to(batch: FramePairBatch, device) -> FramePairBatch:
    """A copy of ``batch`` with every tensor on ``device`` (dtypes unchanged)."""
    return replace(batch, **{n: None if getattr(batch, n) is None else getattr(batch, n).to(device)
                             for n in _BATCH_TENSORS})


def select_pairs(batch: FramePairBatch, index: Sequence[int]) -> FramePairBatch:
    """The pairs ``index`` of ``batch`` as a new batch (in that order)."""
    idx = torch.as_tensor(list(index), dtype=torch.long)
    moved = {}
    for n in _BATCH_TENSORS:
        t = getattr(batch, n)
        moved[n] = None if t is None else t[idx.to(t.device)]
    return replace(batch, ids=[batch.ids[i] for i in index], **moved)


def pair_of(batch: FramePairBatch, k: int) -> FramePair:
    """Pair ``k`` of a batch as a :class:`FramePair` whose tensors are views into the batch."""
    tensors = {n: None if getattr(batch, n) is None else getattr(batch, n)[k]
               for n in _BATCH_TENSORS}
    return FramePair(id=batch.ids[k], **tensors)


def collate_pairs(samples: Sequence[PairSample]) -> PairSampleBatch:
    """Stack samples of equal frame size (the ``collate_fn`` of a ``DataLoader``).

    Raises :class:`~weathergen.errors.ShapeError` naming the sizes when they differ (crop them to
    one size first, e.g. with :class:`~weathergen.training.augment.RandomCrop`).
    """
    samples = list(samples)
    if not samples:
        raise ConfigError("cannot collate an empty list of samples")
    return PairSampleBatch(
        pairs=FramePairBatch.stack([s.pair for s in samples]),
        indices=torch.tensor([s.index for s in samples], dtype=torch.long),
        epochs=torch.tensor([s.epoch for s in samples], dtype=torch.long),
        world_up=[s.world_up for s in samples],
        weather=[s.weather for s in samples],
        particles=[s.particles for s in samples],
    )


class PairDataset(TorchDataset):
    """A weathergen dataset reader as a ``torch.utils.data.Dataset`` of :class:`PairSample`.

    Args:
        dataset: an opened reader (:func:`weathergen.datasets.open_dataset`).
        transform: called on each :class:`PairSample` (for example a
            :class:`~weathergen.training.augment.Compose` of weather, crop and flip).

    Items are looked up by index (the epoch is the one :meth:`set_epoch` set) or by an
    ``(epoch, index)`` tuple, as :class:`EpochSampler` yields them.
    """

    def __init__(self, dataset: Dataset, transform: Optional[Callable[[PairSample], PairSample]] = None):
        if not isinstance(dataset, Dataset):
            raise ConfigError(f"PairDataset needs an opened weathergen dataset, got "
                              f"{type(dataset).__name__}")
        self.dataset = dataset
        self.refs = list(dataset.pairs())     # listed once: file names only
        self.transform = transform
        self.world_up = getattr(dataset, "world_up", "auto")
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Draw the next items for ``epoch`` (call before iterating a ``DataLoader``)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.refs)

    def __getitem__(self, key) -> PairSample:
        epoch, index = key if isinstance(key, tuple) else (self.epoch, key)
        index = int(index)
        if not -len(self.refs) <= index < len(self.refs):
            raise IndexError(f"pair index {index} out of range for {len(self.refs)} pairs")
        index %= len(self.refs)
        sample = PairSample(pair=self.dataset.load(self.refs[index]), index=index,
                            epoch=int(epoch), world_up=self.world_up)
        return sample if self.transform is None else self.transform(sample)


class EpochSampler(Sampler):
    """Wraps a sampler so that it yields ``(epoch, index)`` keys (for persistent workers).

    Call :meth:`set_epoch` before each epoch, as with ``DistributedSampler``.
    """

    def __init__(self, sampler: Sampler | Sequence[int]):
        self.sampler = sampler
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        epoch = self.epoch
        for index in self.sampler:
            yield epoch, int(index)

    def __len__(self) -> int:
        return len(self.sampler)


__all__ = ["EpochSampler", "PairDataset", "PairSample", "PairSampleBatch", "batch_to",
           "collate_pairs", "pair_of", "select_pairs"]
