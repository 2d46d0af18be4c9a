"""Particle-metadata files: one ``.npz`` per pair holding the particle record and its identity.

The file is the particle record of :meth:`weathergen.engine.Particles.to_numpy` (a combined
preset's: :meth:`weathergen.engine.LayeredParticles.to_numpy`, with ``layer_seeds``) plus the
entries of :data:`METADATA_KEYS` (which pair, seed and preset the particles belong to, which files
the pair wrote). It is written last, so a pair whose metadata loads is complete. Particles of a
paper preset also carry ``frame_scaling`` (JSON: the count and size used on the pair's frame size
and the rule that gave them, :meth:`weathergen.engine.FrameScaling.to_dict`; a combined preset's
``{"layers": [...]}``, one per layer); files written before it existed lack it and still read
(:func:`stored_frame_scaling` returns None for them).

Metadata version 2 (written now) gathers the 0-d entries in one ``scalars`` entry
(:mod:`weathergen.io.npz`; ``metadata_version`` and ``format_version`` stay entries of their
own), which saves about 170 bytes per entry; :func:`read_metadata` gives them back as their own
arrays, and reads version 1 files (one entry per value) as well.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .. import __version__
from ..errors import FormatError
from ..framepair import PairId
from ..engine.records.particles import VERSION_ENTRIES
from ..io.atomic import atomic_write_bytes
from ..io.npz import npz_bytes, read_npz

METADATA_VERSION = 2
#: Entries every particle-metadata file holds besides the particle record itself.
METADATA_KEYS = ("metadata_version", "pair_dataset", "pair_split", "pair_scene", "pair_frame", "seed",
                 "preset_name", "preset", "weathergen_version", "files")
#: The optional entry saying how a paper preset's count and size were set for the pair's frame.
FRAME_SCALING = "frame_scaling"


def write_metadata(path: Path, arrays: dict[str, np.ndarray]) -> Path:
    """Write a compressed ``.npz`` atomically (0-d entries gathered, see the module doc)."""
    return atomic_write_bytes(path, npz_bytes(arrays, keep=VERSION_ENTRIES))


def read_metadata(path: str | Path) -> dict[str, np.ndarray]:
    """Load a particle-metadata ``.npz`` (every array), checking its format version and entries."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            magic = f.read(4)
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except OSError as exc:
        raise FormatError(path, f"cannot be read ({exc.strerror})") from None
    if magic != b"PK\x03\x04":   # an .npz is a zip archive; anything else is not one of ours
        raise FormatError(path, "not a .npz archive, so not a weathergen particle-metadata file")
    try:
        arrays = read_npz(path)
    except Exception as exc:  # zipfile/numpy raise several types for corrupt files
        raise FormatError(path, f"not a readable .npz metadata file ({exc})") from None
    if "metadata_version" not in arrays:
        raise FormatError(path, "not a weathergen particle-metadata file (no metadata_version)")
    version = int(arrays["metadata_version"])
    if version > METADATA_VERSION:
        raise FormatError(path, f"metadata format version {version} is newer than this weathergen "
                                f"understands ({METADATA_VERSION}); upgrade weathergen")
    missing = [k for k in METADATA_KEYS if k not in arrays]
    if missing:
        raise FormatError(path, f"incomplete particle-metadata file: no {', '.join(missing)}")
    return arrays


def pair_identity(arrays: dict[str, np.ndarray]) -> PairId:
    """The pair a metadata file belongs to."""
    return PairId(str(arrays["pair_dataset"]), str(arrays["pair_split"]), str(arrays["pair_scene"]),
                  int(arrays["pair_frame"]))


def identity_arrays(pair_id: PairId, seed: int, preset: dict, preset_name: str) -> dict[str, np.ndarray]:
    """The metadata entries that say which pair, seed and preset a particle set belongs to."""
    return {
        "metadata_version": np.array(METADATA_VERSION, np.int32),
        "pair_dataset": np.array(pair_id.dataset), "pair_split": np.array(pair_id.split),
        "pair_scene": np.array(pair_id.scene), "pair_frame": np.array(pair_id.frame, np.int64),
        "seed": np.array(seed, np.uint64), "preset_name": np.array(preset_name),
        "preset": np.array(json.dumps(preset, sort_keys=True)),
        "weathergen_version": np.array(__version__),
    }


def pair_metadata(particles, pair_id: PairId, seed: int, preset: dict, preset_name: str,
                  layer_seeds: Optional[Sequence[int]] = None, *,
                  scaling: Optional[dict] = None) -> dict[str, np.ndarray]:
    """The metadata of one pair: the particle record at storage precision and its identity.

    A combined preset's :class:`~weathergen.engine.LayeredParticles` are stored in their layered
    format (every particle's layer index included); ``layer_seeds``, one per layer, are recorded
    as ``layer_seeds`` beside the pair's ``seed``. ``scaling`` (paper presets) says how the
    preset's count and size were set for the pair's frame; it is stored as ``frame_scaling``."""
    arrays = particles.to_numpy()
    arrays.update(identity_arrays(pair_id, seed, preset, preset_name))
    if layer_seeds is not None:
        arrays["layer_seeds"] = np.array(list(layer_seeds), np.uint64)
    if scaling is not None:
        arrays[FRAME_SCALING] = np.array(json.dumps(scaling, sort_keys=True))
    return arrays


def stored_frame_scaling(arrays: dict[str, np.ndarray], path: str | Path = "") -> Optional[dict]:
    """The ``frame_scaling`` entry of a metadata file's arrays, None when the file has none (a
    weather field's, or written before the entry existed: its count was the preset's as given).
    FormatError names ``path`` when the entry is not JSON."""
    if FRAME_SCALING not in arrays:
        return None
    try:
        return json.loads(str(arrays[FRAME_SCALING]))
    except ValueError:
        raise FormatError(path, f"its {FRAME_SCALING} entry is not valid JSON") from None
