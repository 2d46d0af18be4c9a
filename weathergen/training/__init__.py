"""Training with weather: datasets for PyTorch, weather as an on-the-fly augmentation, RAFT's recipe.

    from weathergen.training import (Compose, PairDataset, RandomCrop, RandomFlip,
                                     WeatherAugment, collate_pairs)

- :mod:`.datasets`: any weathergen reader as a ``torch.utils.data.Dataset`` of frame pairs, and a
  collate function for batches of equal-size pairs;
- :mod:`.augment`: :class:`WeatherAugment` (random weather from presets with probability ``p``,
  draws keyed by ``(seed, epoch, index)``, per sample in workers or per batch on the device), then
  random crops and flips;
- :mod:`.recipe`: RAFT's sequence loss, AdamW with the one-cycle schedule, one training step.
"""

from .augment import (Compose, PresetSource, RandomCrop, RandomFlip, WeatherAugment, WeatherDraw,
                      WeatherSource, crop_pair, flip_pair, keyed_digest)
from .datasets import (EpochSampler, PairDataset, PairSample, PairSampleBatch, batch_to,
                       collate_pairs, pair_of, select_pairs)
from .recipe import (SINTEL_STAGE, end_point_error, freeze_batch_norm, raft_optimizer,
                     sequence_loss, train_step)

__all__ = ["Compose", "EpochSampler", "PairDataset", "PairSample", "PairSampleBatch",
           "PresetSource", "RandomCrop", "RandomFlip", "SINTEL_STAGE", "WeatherAugment",
           "WeatherDraw", "WeatherSource", "batch_to", "collate_pairs", "crop_pair",
           "end_point_error", "flip_pair", "freeze_batch_norm", "keyed_digest", "pair_of",
           "raft_optimizer", "select_pairs", "sequence_loss", "train_step"]
