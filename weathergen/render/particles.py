"""Which particles a pair gets: sampled from the pair's own seed, or loaded from an earlier output.

Render and attack share this rule, so ``attack --seed S`` starts from the weather that
``render --seed S`` writes for the same preset, and both take stored particles the same way.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Optional

from ..engine import Particles, Preset, sample_particles
from ..framepair import FramePair, PairId
from ..outputs.reading import load_pair_particles


def pair_seed(run_seed: int, pair_id: PairId) -> int:
    """A 63-bit seed for one pair, from the run seed and the pair's identity alone."""
    digest = hashlib.sha256(f"weathergen:{run_seed}:{pair_id.key}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def pair_particles(pair: FramePair, preset: Preset, run_seed: int, *, world_up: str = "auto",
                   particles_from: Optional[Path] = None,
                   appearance: Optional[dict] = None, preset_name: Optional[str] = None) -> Particles:
    """The particles of ``pair``: sampled from ``preset`` with the pair's seed, or, with
    ``particles_from``, the ones stored there for the pair, with the ``appearance`` settings
    replaced (see :func:`weathergen.render.resolve_preset`); they must have been sampled from
    ``preset`` (up to its appearance keys) and, when given, be labelled ``preset_name``."""
    if particles_from is None:
        return sample_particles(pair, preset, pair_seed(run_seed, pair.id), world_up=world_up)
    # stored particles must be of the preset the output is labelled with (the stored manifest's)
    particles = load_pair_particles(particles_from, pair.id, preset_name, preset.to_dict())
    if not appearance:
        return particles
    return particles.replace(settings=particles.settings.replace(**appearance))
