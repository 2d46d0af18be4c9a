"""Reading a render or attack output back: its weather frames, its pairs and stored particles.

What ``evaluate`` (the weather frames of every complete pair), ``preview`` and re-rendering or
attacking stored particles (``particles_from``) need from an output folder.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import torch

from ..datasets import Dataset, reopen_dataset
from ..engine import APPEARANCE_KEYS, LayeredParticles, Particles, load_particles
from ..engine.weather.presets import UNSCALED
from ..errors import DatasetError, FormatError
from ..framepair import PairId
from .manifest import read_manifest
from .metadata import pair_identity, read_metadata
from .pairs import PairOutput


def load_pair_particles(folder: str | Path, pair_id: PairId, preset_name: Optional[str] = None,
                        preset: Optional[dict] = None, sequence: bool = False
                        ) -> Particles | LayeredParticles:
    """The particles an earlier render (or attack) stored in ``folder`` for ``pair_id``
    (``sequence``: a ``render --sequence`` folder, whose scenes hold every frame): a
    :class:`~weathergen.engine.Particles` record, or a combined preset's
    :class:`~weathergen.engine.LayeredParticles` (every layer).

    With ``preset_name`` and ``preset`` (a ``Preset.to_dict()``: what the new output will be
    labelled with), the stored particles must have been sampled from that preset (up to the
    appearance keys, which may change).

    Raises FormatError naming the file when it is missing or belongs to another pair, dataset or
    preset.
    """
    path = PairOutput.of(folder, pair_id, "", sequence=sequence).metadata
    if not path.exists():
        raise FormatError(path, f"no particle metadata for pair {pair_id}")
    check_stored_particles(path, read_metadata(path), pair_id, preset_name, preset)
    return load_particles(path)


def check_stored_particles(path: str | Path, arrays: dict, pair_id: PairId,
                           preset_name: Optional[str] = None, preset: Optional[dict] = None) -> None:
    """Refuse a metadata file that does not belong to this pair and dataset (and, when given, to
    this preset); :class:`FormatError` names the file and what differs."""
    found = pair_identity(arrays)
    if (found.scene, found.frame) != (pair_id.scene, pair_id.frame):
        raise FormatError(path, f"metadata belongs to {found.scene} frame {found.frame}, "
                                f"not to {pair_id.scene} frame {pair_id.frame}")
    if (found.dataset, found.split) != (pair_id.dataset, pair_id.split):
        raise FormatError(path, f"metadata belongs to the {found.split} split of dataset "
                                f"{found.dataset!r}, not to the {pair_id.split} split of "
                                f"{pair_id.dataset!r}")
    if preset_name is not None:
        stored_name = str(arrays["preset_name"])
        if stored_name != preset_name:
            raise FormatError(path, f"particles of preset {stored_name!r}, but the folder's "
                                    f"manifest says {preset_name!r}")
    if preset is not None:
        try:
            stored = json.loads(str(arrays["preset"]))
        except ValueError:
            raise FormatError(path, "its preset entry is not valid JSON") from None
        if "model" not in stored:     # a paper preset recorded before frame scaling existed
            stored = {**UNSCALED, **stored}
        ignored = {"name", "source", *APPEARANCE_KEYS}
        differ = sorted(k for k in set(stored) | set(preset)
                        if k not in ignored and stored.get(k) != preset.get(k))
        if differ:
            raise FormatError(path, f"particles sampled with other preset settings than the "
                                    f"folder's manifest records ({', '.join(differ)})")


@dataclass
class WeatherFolder:
    """A render (or attack) output opened for reading.

    Attributes: root; pass_name (the folder of the weather frames); fmt (png, exr or both);
    input (the manifest's description of the clean dataset); pairs (complete pairs, sorted).
    """

    root: Path
    pass_name: str
    fmt: str
    input: dict
    pairs: list
    sequence: bool = False        # a `render --sequence` tree: scenes hold every frame
    #: with ``skip_unreadable``: what is wrong with each particle file that cannot be read
    unreadable: list = field(default_factory=list)

    @classmethod
    def open(cls, root: str | Path, skip_unreadable: bool = False) -> "WeatherFolder":
        """The output at ``root``. A particle-metadata file that cannot be read raises
        FormatError naming it, or with ``skip_unreadable`` leaves its pair out and is listed in
        ``unreadable`` (one line each)."""
        root = Path(root)
        manifest = read_manifest(root, "weather")
        pass_name, fmt = manifest.pass_name, manifest.fmt
        pairs, unreadable = [], []
        for meta in sorted(root.glob("*/particles/*/frame_*.npz")):
            try:
                pid = pair_identity(read_metadata(meta))
            except FormatError as exc:
                if not skip_unreadable:
                    raise
                unreadable.append(f"{exc}; its pair is left out")
                continue
            if PairOutput.of(root, pid, pass_name, fmt, sequence=manifest.sequence).is_complete():
                pairs.append(pid)
        if not pairs:
            why = f" ({unreadable[0]})" if unreadable else ""
            raise DatasetError(f"{root}: holds no complete weather pairs{why}")
        return cls(root, pass_name, fmt, manifest.input, sorted(pairs), manifest.sequence,
                   unreadable)

    def frames(self, pair_id: PairId) -> tuple[torch.Tensor, torch.Tensor]:
        """The weather frames of a pair. Shape: two (3, H, W) float32 in [0, 1]."""
        out = PairOutput.of(self.root, pair_id, self.pass_name, self.fmt, sequence=self.sequence)
        images = [out.read_frame(i) for i in (0, 1)]        # through the output's format
        return tuple(torch.from_numpy(img.copy()).permute(2, 0, 1).contiguous() for img in images)

    def particles(self, pair_id: PairId) -> Optional[Particles | LayeredParticles]:
        """The particles stored for a pair (every layer of a combined preset), or None where the
        folder holds none (an Lp attack's metadata names the pair and the perturbation only)."""
        path = PairOutput.of(self.root, pair_id, "", sequence=self.sequence).metadata
        arrays = read_metadata(path)
        if "position" not in arrays and "layer_names" not in arrays:
            return None
        return load_pair_particles(self.root, pair_id, sequence=self.sequence)

    def clean_dataset(self, dataset: Optional[str] = None, root: Optional[str] = None,
                      pass_: Optional[str] = None) -> Dataset:
        """The dataset the weather was rendered into (as recorded), or the one given."""
        if dataset is None or dataset == self.input.get("dataset"):
            description = dict(self.input)        # with every recorded reader option
        else:                                     # another reader: its own defaults
            description = {"dataset": dataset, "split": self.input.get("split", "training")}
        if root is not None:
            description["root"] = root
        if pass_ is not None:
            description["pass"] = pass_
        return reopen_dataset(description)
