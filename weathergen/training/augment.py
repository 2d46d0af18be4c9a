"""Weather as an on-the-fly training augmentation, and the geometric augmentations that follow it.

:class:`WeatherAugment` renders random weather from one or more presets into a frame pair with
probability ``p`` and leaves the flow (and everything but the two frames) unchanged. Every random
choice is keyed by ``(seed, epoch, index)``: the same key gives the same bytes whichever worker
process draws it and however many there are, and a new epoch gives new weather.

It runs in one of two places:

- **per sample, in the DataLoader's workers (CPU)**: use the object itself as the dataset's
  transform: ``PairDataset(reader, transform=Compose([weather, RandomCrop(...), RandomFlip(...)]))``;
- **per batch, on the training device**: the workers only draw the particles
  (``transform=weather.prepare``: sampling is CPU work and runs in parallel there), the batch is
  moved to the device and :meth:`WeatherAugment.apply_batch` renders every pair that gets weather
  in one batched call (one per template library when presets with different templates are
  mixed). Without ``prepare`` the batch path samples the particles itself (on the CPU, from the
  pairs' depth and cameras). Both paths render with the engine's one render core
  (:func:`~weathergen.engine.render`), which lays every pair's particles out as ragged runs: a
  batch costs a few hundred tensor operations (kernel launches on a GPU) whatever the particles'
  number and sizes, and on the CPU each pair's frames are bit for bit those of rendering it alone,
  so both paths give the same frames; CUDA's agree with the CPU's within one grey level.

**Order: weather first, geometric augmentation after.** The weather is drawn for the whole frame
(a paper preset's count follows the frame's area) and a crop shows part of it, particles just
outside the crop whose footprints reach in included; an explicit count is per frame, and rendering
into a crop would pack all of it into the crop. :class:`RandomCrop` and :class:`RandomFlip` (which
update the intrinsics and poses, so the pair stays a consistent record) therefore come after the
weather, on samples or on batches, with their own ``(seed, epoch, index)`` draws.

Other weather models plug in as a :class:`WeatherSource`: anything with a ``name``, the name of
its template library and ``sample(pair, seed, world_up) -> Particles``. Presets of either model
(the paper's, and the world-unit weather fields such as ``snow-light``) are
:class:`PresetSource`; a source whose particles carry ground truth can be used with
``keep_particles=True``, which keeps each rendered particle record in the sample.
"""

from __future__ import annotations

import hashlib
import os
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Mapping, Optional, Protocol, Sequence, Union, runtime_checkable

import torch

from ..datasets import frame_rate_of
from ..engine import (CombinedPreset, FieldPreset, LayeredParticles, Preset, load_preset, load_templates, render_pair,
                      sample_weather)
from ..errors import ConfigError, ShapeError
from ..framepair import FramePair, FramePairBatch
from .datasets import (PairSample, PairSampleBatch, batch_to, collate_pairs, pair_of,
                       select_pairs)


# ---------------------------------------------------------------------------------------------
# Keyed draws
# ---------------------------------------------------------------------------------------------

def keyed_digest(kind: str, seed: int, epoch: int, index: int) -> bytes:
    """32 bytes that depend on the transform kind, its seed, the epoch and the sample index only."""
    return hashlib.sha256(f"weathergen-train:{kind}:{seed}:{epoch}:{index}".encode()).digest()


def _uniform(digest: bytes, slot: int) -> float:
    """A number in [0, 1) from 8 bytes of ``digest`` (slots 0..3)."""
    return int.from_bytes(digest[8 * slot: 8 * slot + 8], "big") / 2.0 ** 64


def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"seed {seed!r}: must be an integer")
    return seed


def _check_probability(name: str, p) -> float:
    if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 <= p <= 1.0:
        raise ConfigError(f"{name} {p!r}: must be a probability in [0, 1]")
    return float(p)


# ---------------------------------------------------------------------------------------------
# Weather sources
# ---------------------------------------------------------------------------------------------

@runtime_checkable
class WeatherSource(Protocol):
    """A weather model the augmentation can draw from.

    ``sample`` returns the particles for one pair from an integer seed (the same seed, the same
    particles); ``templates`` names the template library they are rendered with, so that pairs
    whose particles share it are rendered in one call.
    """

    name: str
    templates: str

    def sample(self, pair: FramePair, seed: int, world_up: str):
        ...


#: Loaded presets of every kind.
_PRESET_TYPES = (Preset, FieldPreset, CombinedPreset)


class PresetSource:
    """One preset of either weather model, sampled as ``weathergen render`` samples it
    (:func:`~weathergen.engine.sample_weather`): a paper preset places its ``count`` visible
    particles in the pair (:func:`~weathergen.engine.sample_particles`); a weather-field preset
    (``model = "field"``, world units: ``snow-light``, ``rain-heavy``, ...) draws the pair's
    particles from the field of the draw's seed (:func:`~weathergen.engine.sample_field_particles`),
    so every sample gets a field of its own and the same density in scene units. A combined
    preset (``"rain-heavy+fog-light"``) samples every layer and renders them in one pass, in
    depth order (see ``docs/engine.md``, "Combined presets").

    Args:
        preset: a bundled preset name, a path to a ``.toml`` file, presets joined by ``+``, or
            a loaded :class:`Preset`, :class:`FieldPreset` or :class:`CombinedPreset`.
        overrides: preset keys to change, as for ``--set`` (``{"count": 1500}``,
            ``{"density": 60}``).
    """

    def __init__(self, preset: Union[str, Path, Preset, FieldPreset, CombinedPreset],
                 overrides: Optional[Mapping] = None, name: Optional[str] = None):
        if isinstance(preset, _PRESET_TYPES):
            if overrides:
                raise ConfigError("overrides apply to presets given by name or path, "
                                  "not to a loaded Preset")
            self.preset = preset
            # unnamed: eight hex digits that identify the preset's resolved values
            digest = hashlib.sha256(repr(sorted(preset.to_dict().items())).encode()).hexdigest()
            self.name = name or f"preset-{digest[:8]}"
        else:
            try:
                self.preset = load_preset(preset, overrides=dict(overrides or {}))
            except ConfigError as exc:     # name the preset an override did not fit
                if str(preset) in str(exc):
                    raise
                raise ConfigError(f"preset {preset}: {exc}") from None
            self.name = name or (Path(str(preset)).stem if str(preset).endswith(".toml")
                                 else str(preset))
        if isinstance(self.preset, CombinedPreset):    # each layer is drawn with its own
            self.templates = "+".join(layer.templates for layer in self.preset.layers)
        else:
            self.templates = self.preset.templates

    @property
    def model(self) -> str:
        """``"field"`` for a weather-field preset, ``"paper"`` for the paper's model,
        ``"combined"`` for layers of either."""
        if isinstance(self.preset, CombinedPreset):
            return "combined"
        return "field" if isinstance(self.preset, FieldPreset) else "paper"

    def sample(self, pair: FramePair, seed: int, world_up: str, sample_on=None):
        """The particles of ``pair`` from ``seed``; a field moves at the frame rate of the pair's
        dataset (its reader's, looked up by the name the pair carries). A combined preset gives
        :class:`~weathergen.engine.LayeredParticles`, every layer from its own seed derived from
        ``seed`` (:func:`~weathergen.engine.layer_seed`). ``sample_on``: the device of the
        sampling arithmetic (:func:`~weathergen.engine.sample_weather`), the record's too."""
        combined = isinstance(self.preset, CombinedPreset)
        return sample_weather(pair, self.preset, seed, world_up=world_up,
                              frame_rate=frame_rate_of(pair.id.dataset),
                              templates=None if combined else load_templates(self.templates),
                              sample_on=sample_on, device=sample_on)

    def __repr__(self) -> str:
        return f"PresetSource({self.name!r})"


def _render_group(record) -> tuple:
    """Records one render call takes together: those of one template library, or combined
    weather of the same layers' libraries."""
    if isinstance(record, LayeredParticles):
        return tuple(r.settings.templates for r in record.layers)
    return (record.settings.templates,)


def _is_source(obj) -> bool:
    return not isinstance(obj, (str, Path, *_PRESET_TYPES)) and isinstance(obj, WeatherSource)


# ---------------------------------------------------------------------------------------------
# The weather transform
# ---------------------------------------------------------------------------------------------

#: Where :meth:`WeatherAugment.apply_batch` samples particles (its ``sample_on``).
SAMPLE_ON = ("cpu", "device")


@dataclass(frozen=True)
class WeatherDraw:
    """What the weather transform drew for one sample.

    Attributes:
        applied: whether the sample gets weather (probability ``p``).
        source: the name of the preset or source drawn, ``None`` when not applied.
        seed: the particle seed (63-bit), ``None`` when not applied.
        rendered: whether the weather is in the frames yet (``prepare`` draws without rendering).
    """

    applied: bool
    source: Optional[str] = None
    seed: Optional[int] = None
    rendered: bool = False


class WeatherAugment:
    """Render random weather into frame pairs with probability ``p``; the flow stays as it is.

    Args:
        presets: one or more presets (names, ``.toml`` paths, :class:`Preset` objects) or
            :class:`WeatherSource` objects; each sample that gets weather draws one of them with
            equal probability.
        p: probability that a sample gets weather (the paper's best training used 0.5 with snow).
        seed: seed of every draw; draws are keyed by ``(seed, epoch, index)``.
        overrides: preset keys changed for every preset given by name or path (for example
            ``{"count": 1000}``: exactly 1000 particles, where a paper preset's own count scales
            with each frame's area).
        world_up: which world axis points up; ``None`` takes each sample's (its dataset's) setting.
        keep_particles: keep the rendered particle record in :attr:`PairSample.particles`.
        sample_on: where :meth:`apply_batch` samples the particles it has to sample itself:
            ``"cpu"`` (from the batch's depth and cameras copied to the CPU, in threads) or
            ``"device"`` (the batch's device: the same random numbers from the same CPU
            generators, the arithmetic where the depth maps are; on a GPU the particles equal the
            CPU's but for candidates within rounding of a border, see ``docs/engine.md``). Only
            presets (of either model) sample on a device; other sources sample on the CPU.

    Shape: frames ``(3, H, W)`` per sample or ``(B, 3, H, W)`` per batch, RGB in ``[0, 1]``;
    the pairs need depth and cameras (every weathergen reader provides them).
    """

    def __init__(self, presets: Union[str, Preset, WeatherSource, Sequence] = ("snow",),
                 p: float = 0.5, seed: int = 0, *, overrides: Optional[Mapping] = None,
                 world_up: Optional[str] = None, keep_particles: bool = False,
                 sample_on: str = "cpu"):
        single = isinstance(presets, (str, Path, *_PRESET_TYPES)) or _is_source(presets)
        items = [presets] if single else list(presets)
        if not items:
            raise ConfigError("WeatherAugment needs at least one preset")
        self.sources = [s if _is_source(s) else
                        PresetSource(s, None if isinstance(s, _PRESET_TYPES) else overrides)
                        for s in items]
        names = [s.name for s in self.sources]
        if len(set(names)) != len(names):
            raise ConfigError(f"weather sources need distinct names, got {', '.join(names)}")
        self.p = _check_probability("p", p)
        self.seed = _check_seed(seed)
        self.world_up = world_up
        self.keep_particles = bool(keep_particles)
        if sample_on not in SAMPLE_ON:
            raise ConfigError(f"sample_on {sample_on!r}: expected {' or '.join(SAMPLE_ON)}")
        self.sample_on = sample_on

    def __repr__(self) -> str:
        names = ", ".join(s.name for s in self.sources)
        return f"WeatherAugment([{names}], p={self.p}, seed={self.seed})"

    # -- parameters ------------------------------------------------------------------------
    def draw(self, index: int, epoch: int = 0) -> WeatherDraw:
        """Whether sample ``index`` gets weather in ``epoch``, from which source, with which seed."""
        digest = keyed_digest("weather", self.seed, int(epoch), int(index))
        if not _uniform(digest, 0) < self.p:
            return WeatherDraw(applied=False)
        source = self.sources[int(_uniform(digest, 1) * len(self.sources))]
        seed = int.from_bytes(digest[16:24], "big") >> 1      # 63 bits of the digest's slot 2
        return WeatherDraw(applied=True, source=source.name, seed=seed)

    def _particles(self, pair: FramePair, draw: WeatherDraw, world_up: str, sample_on=None):
        source = next((s for s in self.sources if s.name == draw.source), None)
        if source is None:
            raise ConfigError(f"sample was prepared with weather {draw.source!r}, which this "
                              f"transform does not have ({', '.join(s.name for s in self.sources)})")
        if sample_on is not None and isinstance(source, PresetSource):
            return source.sample(pair, draw.seed, self.world_up or world_up, sample_on=sample_on)
        return source.sample(pair, draw.seed, self.world_up or world_up)

    # -- per sample ------------------------------------------------------------------------
    def prepare(self, sample: PairSample) -> PairSample:
        """Draw for ``sample`` and sample its particles without rendering them (a worker-side
        transform for :meth:`apply_batch`)."""
        draw = self.draw(sample.index, sample.epoch)
        particles = self._particles(sample.pair, draw, sample.world_up) if draw.applied else None
        return replace(sample, weather=draw, particles=particles)

    def __call__(self, sample: PairSample) -> PairSample:
        """Render the sample's weather into its frames (on the sample's device, normally the CPU).

        A sample without weather comes back with the very same pair (bit for bit the input).
        """
        draw, particles = self._pending(sample.weather, sample.particles, sample.index,
                                        sample.epoch)
        if not draw.applied or draw.rendered:
            return replace(sample, weather=draw)
        if particles is None:
            particles = self._particles(sample.pair, draw, sample.world_up)
        out = render_pair(sample.pair, particles)
        pair = replace(sample.pair, image1=out.image1[0], image2=out.image2[0])
        return replace(sample, pair=pair, weather=replace(draw, rendered=True),
                       particles=particles if self.keep_particles else None)

    def _pending(self, weather, particles, index, epoch):
        """The draw to use: the one ``prepare`` made, else a fresh one."""
        if isinstance(weather, WeatherDraw):
            return weather, particles
        return self.draw(index, epoch), None

    # -- per batch -------------------------------------------------------------------------
    def apply_batch(self, batch: PairSampleBatch) -> PairSampleBatch:
        """Render the weather of every sample that gets some, in one batched render call per
        template library, on the device the batch is on (``batch.to("cuda")`` first for a GPU).

        Particles prepared in the workers (:meth:`prepare`) are used as they are; the others are
        sampled here, from the pairs' depth and cameras, on the CPU or (``sample_on="device"``)
        on the batch's device, in threads (one per pair, up to the CPU count; each pair's draw is
        its own, so the particles do not depend on them).
        Shape: ``batch.pairs`` images ``(B, 3, H, W)``; returns a batch of the same shapes.
        """
        pairs = batch.pairs
        draws, records, todo, unsampled = [], [], [], []
        for k in range(len(batch)):
            draw, particles = self._pending(batch.weather[k], batch.particles[k],
                                            int(batch.indices[k]), int(batch.epochs[k]))
            if draw.applied and not draw.rendered:
                if particles is None:
                    unsampled.append(k)
                todo.append(k)
            draws.append(draw)
            records.append(particles)
        if not todo:
            return replace(batch, weather=draws)
        if unsampled:
            for k, particles in zip(unsampled, self._sample_batch(batch, draws, unsampled)):
                records[k] = particles

        groups = defaultdict(list)
        for k in todo:                    # one render call per template library (or layers')
            groups[_render_group(records[k])].append(k)
        image1, image2 = pairs.image1, pairs.image2
        whole = len(groups) == 1 and len(todo) == len(batch)
        if not whole:                     # filled in place, group by group
            image1, image2 = image1.clone(), image2.clone()
        for members in groups.values():
            group = [records[k] for k in members]
            chosen = pairs if whole else select_pairs(pairs, members)
            out = render_pair(chosen, group)
            if whole:
                image1, image2 = out.image1, out.image2
            else:
                index = torch.tensor(members, device=image1.device)
                image1[index] = out.image1
                image2[index] = out.image2
            for k in members:
                draws[k] = replace(draws[k], rendered=True)
        kept = [r if self.keep_particles else None for r in records]
        return replace(batch, pairs=replace(pairs, image1=image1, image2=image2), weather=draws,
                       particles=kept)

    def _sample_batch(self, batch: PairSampleBatch, draws: list, unsampled: list) -> list:
        """Particles for the samples ``unsampled`` of ``batch``, in threads (see
        :meth:`apply_batch`)."""
        pairs = batch.pairs
        on_device = self.sample_on == "device" and pairs.image1.device.type != "cpu"
        geometry = pairs if on_device else _geometry_on_cpu(pairs)
        where = pairs.image1.device if on_device else None

        def sample(k):
            return self._particles(pair_of(geometry, k), draws[k], batch.world_up[k], where)

        threads = min(len(unsampled), os.cpu_count() or 1)
        if threads > 1:
            with ThreadPoolExecutor(threads) as pool:
                return list(pool.map(sample, unsampled))
        return [sample(k) for k in unsampled]


def _geometry_on_cpu(pairs: FramePairBatch) -> FramePairBatch:
    """What particle sampling reads (depth and cameras) on the CPU; the images, which it does
    not read, are stand-ins of the right shape, so a GPU batch is not copied back whole."""
    if pairs.image1.device.type == "cpu":
        return pairs
    stand_in = torch.zeros((), dtype=pairs.image1.dtype).expand(pairs.image1.shape)
    cpu = batch_to(replace(pairs, image1=stand_in, image2=stand_in, flow=None, flow_valid=None),
                   "cpu")
    return cpu


# ---------------------------------------------------------------------------------------------
# Geometric augmentation (after the weather)
# ---------------------------------------------------------------------------------------------

_PIXEL_FIELDS = ("image1", "image2", "depth1", "depth2", "flow", "flow_valid",
                 "depth_provenance1", "depth_provenance2")


def crop_pair(pair: FramePair, top: int, left: int, height: int, width: int) -> FramePair:
    """The window ``[top, top + height) x [left, left + width)`` of every per-pixel tensor; the
    principal point moves with it, so depth and cameras still describe the cropped frames."""
    h, w = pair.size
    if not (0 <= top and top + height <= h and 0 <= left and left + width <= w):
        raise ShapeError(f"{pair.id}: crop {height}x{width} at ({top}, {left}) does not fit "
                           f"the {h}x{w} frames")
    moved = {n: None if getattr(pair, n) is None
             else getattr(pair, n)[..., top:top + height, left:left + width]
             for n in _PIXEL_FIELDS}
    k = pair.intrinsics.clone()
    k[0, 2] -= left
    k[1, 2] -= top
    return replace(pair, intrinsics=k, **moved)


def flip_pair(pair: FramePair, horizontal: bool, vertical: bool) -> FramePair:
    """Mirror the pair left-right and/or top-bottom.

    The flow's ``u`` (``v``) changes sign; the principal point is mirrored; the poses become those
    of the mirrored world (``S E S`` with ``S = diag(-1, 1, 1, 1)`` or ``diag(1, -1, 1, 1)``), so
    they stay proper rigid transforms and the record stays consistent.
    """
    if not (horizontal or vertical):
        return pair
    h, w = pair.size
    dims = ([-1] if horizontal else []) + ([-2] if vertical else [])
    moved = {n: None if getattr(pair, n) is None else torch.flip(getattr(pair, n), dims)
             for n in _PIXEL_FIELDS}
    if moved["flow"] is not None:
        sign = torch.tensor([-1.0 if horizontal else 1.0, -1.0 if vertical else 1.0],
                            dtype=moved["flow"].dtype, device=moved["flow"].device)
        moved["flow"] = moved["flow"] * sign[:, None, None]
    k = pair.intrinsics.clone()
    if horizontal:
        k[0, 2] = (w - 1) - k[0, 2]
    if vertical:
        k[1, 2] = (h - 1) - k[1, 2]
    s = torch.diag(torch.tensor([-1.0 if horizontal else 1.0, -1.0 if vertical else 1.0, 1.0, 1.0],
                                dtype=torch.float64, device=pair.intrinsics.device))

    def mirror(t):
        return None if t is None else s.to(t.dtype) @ t @ s.to(t.dtype)

    return replace(pair, intrinsics=k, cam2_from_cam1=mirror(pair.cam2_from_cam1),
                   cam1_from_world=mirror(pair.cam1_from_world),
                   cam2_from_world=mirror(pair.cam2_from_world), **moved)


class _PerSample:
    """A sample transform whose batch form applies it to every sample and stacks the results."""

    def apply_batch(self, batch: PairSampleBatch) -> PairSampleBatch:
        return collate_pairs([self(batch.sample(k)) for k in range(len(batch))])


class RandomCrop(_PerSample):
    """A random ``size = (height, width)`` window per sample (RAFT's Sintel stage: 368 x 768).

    The window is drawn from ``(seed, epoch, index)``; frames smaller than ``size`` are an error.
    """

    def __init__(self, size: tuple[int, int], seed: int = 0):
        if len(size) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in size):
            raise ConfigError(f"crop size {size!r}: must be (height, width) in pixels")
        self.size = (int(size[0]), int(size[1]))
        self.seed = _check_seed(seed)

    def __call__(self, sample: PairSample) -> PairSample:
        (h, w), (ch, cw) = sample.pair.size, self.size
        if ch > h or cw > w:
            raise ShapeError(f"{sample.pair.id}: frames of {h}x{w} are smaller than the "
                               f"{ch}x{cw} crop")
        digest = keyed_digest("crop", self.seed, sample.epoch, sample.index)
        top = int(_uniform(digest, 0) * (h - ch + 1))
        left = int(_uniform(digest, 1) * (w - cw + 1))
        return replace(sample, pair=crop_pair(sample.pair, top, left, ch, cw))


class RandomFlip(_PerSample):
    """Mirror left-right with probability ``horizontal``, top-bottom with ``vertical`` (RAFT's
    Sintel stage: 0.5 and 0.1), drawn from ``(seed, epoch, index)``."""

    def __init__(self, horizontal: float = 0.5, vertical: float = 0.1, seed: int = 0):
        self.horizontal = _check_probability("horizontal flip probability", horizontal)
        self.vertical = _check_probability("vertical flip probability", vertical)
        self.seed = _check_seed(seed)

    def __call__(self, sample: PairSample) -> PairSample:
        digest = keyed_digest("flip", self.seed, sample.epoch, sample.index)
        return replace(sample, pair=flip_pair(sample.pair, _uniform(digest, 0) < self.horizontal,
                                              _uniform(digest, 1) < self.vertical))


class Compose:
    """Apply transforms in order, to a sample (``compose(sample)``) or to a batch
    (``compose.apply_batch(batch)``)."""

    def __init__(self, transforms: Sequence):
        self.transforms = list(transforms)

    def __call__(self, sample: PairSample) -> PairSample:
        for t in self.transforms:
            sample = t(sample)
        return sample

    def apply_batch(self, batch: PairSampleBatch) -> PairSampleBatch:
        for t in self.transforms:
            batch = t.apply_batch(batch)
        return batch

    def __repr__(self) -> str:
        return f"Compose({self.transforms!r})"


__all__ = ["Compose", "PresetSource", "RandomCrop", "RandomFlip", "WeatherAugment",
           "WeatherDraw", "WeatherSource", "crop_pair", "flip_pair", "keyed_digest"]
