"""Which particles a pair gets: sampled from the pair's own seed, or loaded from an earlier output.

Render and attack share this rule, so ``attack --seed S`` starts from the weather that
``render --seed S`` writes for the same preset, and both take stored particles the same way.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Optional, Sequence

from ..engine import (CombinedPreset, FieldPreset, LayeredParticles, Particles, Preset, frame_scaling,
                      layer_seed, sample_weather, scene_seed)
from ..datasets import PairRef
from ..engine.sampling.field import pair_airlight
from ..engine.sampling.published import published_particles
from ..errors import WeatherGenError
from ..framepair import FramePair, PairId
from ..io.published_weather import is_published_set, published_file, read_published_weather
from ..outputs.reading import load_pair_particles


def pair_seed(run_seed: int, pair_id: PairId) -> int:
    """A 63-bit seed for one pair, from the run seed and the pair's identity alone."""
    digest = hashlib.sha256(f"weathergen:{run_seed}:{pair_id.key}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def weather_seed(preset, run_seed: int, pair_id: PairId) -> int:
    """The seed a pair's weather is drawn from: the pair's own for the paper's model, the scene's
    for a weather field (so that the pairs of a scene share one field and their common frames).
    A combined preset's is the pair's own; each layer has its own (:func:`layer_seeds`)."""
    if isinstance(preset, FieldPreset):
        return scene_seed(run_seed, pair_id.dataset, pair_id.split, pair_id.scene)
    return pair_seed(run_seed, pair_id)


def layer_seeds(preset: CombinedPreset, run_seed: int, pair_id: PairId) -> tuple[int, ...]:
    """The seed of each layer of a combined preset for one pair: derived by the layer's name from
    the seed its preset alone would get (:func:`weather_seed`), so a field layer is one field over
    its scene and a paper layer is the pair's own, and the layers never share random numbers."""
    return tuple(layer_seed(weather_seed(layer, run_seed, pair_id), layer.name)
                 for layer in preset.layers)


def weather_scaling(preset, pair: FramePair, particles_from: Optional[Path] = None) -> Optional[dict]:
    """How a paper preset's count and size are set for the pair's frame size (the particle
    metadata's ``frame_scaling`` entry); None for a weather field (world units: nothing scales)
    and for the paper's published weather (its files fix the particles); for a combined preset
    ``{"layers": [...]}``, one entry (or None) per layer."""
    if particles_from is not None and is_published_set(particles_from):
        return None
    if isinstance(preset, CombinedPreset):
        return {"layers": [weather_scaling(layer, pair) for layer in preset.layers]}
    if isinstance(preset, FieldPreset):
        return None
    return frame_scaling(preset, *pair.size).to_dict()


def pair_particles(pair: FramePair, preset: Preset, run_seed: int, *, world_up: str = "auto",
                   frame_rate: Optional[float] = None, particles_from: Optional[Path] = None,
                   appearance: Optional[dict] = None, preset_name: Optional[str] = None,
                   sequence: bool = False, airlight: Optional[Sequence[float]] = None
                   ) -> Particles | LayeredParticles:
    """The particles of ``pair``: sampled from ``preset`` with the pair's seed (the scene's for a
    weather field, see :func:`weather_seed`; a combined preset's layers with :func:`layer_seeds`,
    as :class:`~weathergen.engine.LayeredParticles`; ``world_up`` and ``frame_rate`` are the
    dataset's, as its reader declares them; ``airlight``: an ``auto`` airlight of the scene,
    :func:`scene_airlight`), or, with ``particles_from``, the ones stored there for
    the pair (``sequence``: a ``render --sequence`` folder), with the ``appearance`` settings
    replaced (see :func:`weathergen.render.resolve_preset`); they must have been sampled from
    ``preset`` (up to its appearance keys) and, when given, be labelled ``preset_name``. A
    published set of the paper's weather (the research code's files, one per pair) gives the
    pair's file mapped into the pair (:func:`~weathergen.engine.sampling.published.published_particles`),
    drawn with ``preset``."""
    if particles_from is None:
        seed = (layer_seeds(preset, run_seed, pair.id) if isinstance(preset, CombinedPreset)
                else weather_seed(preset, run_seed, pair.id))
        return sample_weather(pair, preset, seed, world_up=world_up, frame_rate=frame_rate,
                              airlight=airlight)
    if is_published_set(particles_from):   # the research code's files: drawn with ``preset``
        return published_particles(read_published_weather(
            published_file(particles_from, pair.id.scene, pair.id.frame)), pair, preset)
    # stored particles must be of the preset the output is labelled with (the stored manifest's)
    particles = load_pair_particles(particles_from, pair.id, preset_name, preset.to_dict(),
                                    sequence=sequence)
    if not appearance:
        return particles
    return particles.replace(settings=particles.settings.replace(**appearance))


def selected_pairs(dataset, particles_from: Optional[Path], on_note) -> list:
    """The dataset's selected pairs; its notes (e.g. a gap in a scene's frame numbering) go to
    ``on_note``, and so does one when the paper's published weather is drawn into a dataset opened
    otherwise than in the research code's frame and scaling (its per-scene depth factors, its
    camera translation zeroed in the scenes it scales): the particles then sit elsewhere than that
    code drew them."""
    refs = dataset.pairs()
    for note in dataset.scene_notes():
        on_note(note)
    research = (getattr(dataset, "scene_scales_bundled", False)
                and getattr(dataset, "camera_translation", None) == "unscaled")
    if particles_from is not None and is_published_set(particles_from) and not research:
        on_note(f"{particles_from} holds the paper's published weather, placed in the research "
                f"code's frame and scaling; to draw it where that code drew it, open the dataset "
                f"as it did: --compat reference, or --scene-scales research "
                f"--no-translation-in-scaled-scenes (docs/render.md)")
    return refs


def scene_key(pair_id: PairId) -> tuple[str, str, str]:
    return pair_id.dataset, pair_id.split, pair_id.scene


def scene_firsts(refs: Sequence[PairRef]) -> dict:
    """Each scene's first selected pair (its lowest frame), by :func:`scene_key`: where a run
    estimates the scene's ``auto`` airlight (:func:`scene_airlight`), whatever its shards."""
    out: dict = {}
    for ref in refs:
        key = scene_key(ref.id)
        if key not in out or ref.id.frame < out[key].id.frame:
            out[key] = ref
    return out


_SCENE_AIRLIGHTS: dict = {}


def scene_airlight(dataset, pair_id: PairId, firsts: dict, preset
                   ) -> Optional[tuple[float, float, float]]:
    """The ``auto`` airlight of the scene of ``pair_id`` for ``preset``'s atmospheres: estimated
    once (per process) from both frames of the scene's first selected pair (``firsts``, from
    :func:`scene_firsts`), so that every pair of a scene, and so every frame of a sequence, shares
    it. None where the preset takes none, or the first pair cannot be read (each pair then
    estimates its own)."""
    layers = preset.layers if isinstance(preset, CombinedPreset) else (preset,)
    # the farthest sky distance of the field layers whose atmosphere takes an auto airlight
    sky = max((p.sky_distance for p in layers if isinstance(p, FieldPreset) and p.has_atmosphere
               and p.airlight == "auto"), default=None)
    first = firsts.get(scene_key(pair_id))
    if sky is None or first is None:
        return None
    key = (json.dumps(dataset.describe(), sort_keys=True, default=str), first.id.key,
           tuple(sorted((k, str(v)) for k, v in first.files.items())), sky)
    if key not in _SCENE_AIRLIGHTS:
        try:
            _SCENE_AIRLIGHTS[key] = pair_airlight(dataset.load(first), sky)
        except WeatherGenError:
            return None
    return _SCENE_AIRLIGHTS[key]
