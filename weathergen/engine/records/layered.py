"""The particles of a combined preset: one record per layer, kept together and stored in one file.

A combined preset (``rain-heavy+fog-light``, :class:`~weathergen.engine.weather.presets.CombinedPreset`)
samples every layer exactly as its preset alone would, from the layer's own seed
(:func:`layer_seed`: the seed and the layer's name, so a layer's particles depend neither on the
other layers nor on their order). :class:`LayeredParticles` keeps the layers' records side by side.
Each layer is an ordinary :class:`~weathergen.engine.Particles` record because the two weather
models' records differ in more than their values: each layer has its own render settings (blend
mode, motion blur, template library), and a paper record's ``scale``, ``defocus`` and
``transparency`` are fixed at sampling (pixels per template pixel, a disc radius, θ after the depth
hat) where a field record carries :class:`~weathergen.engine.FieldOptics` and its ``scale`` is a
diameter in scene units, footprint, defocus and fade following each frame's depth. Every layer
lives in the same reference frame (the pair's).

The particles of all layers, layer after layer, are numbered ``0 .. N - 1``:
:meth:`LayeredParticles.layer_index` gives the layer of each and :meth:`LayeredParticles.concat`
one field over all of them (template indices stay indices into their own layer's library).

Storage (particle format version 4): one ``.npz`` per pair holding

- ``format_version`` (4), ``layer_names`` ``(L,)`` str, ``layer_counts`` ``(L,)`` int64, and
  ``layer`` ``(N,)`` uint8: the layer of every particle, in that numbering;
- for layer ``k``, every entry of that layer's own record file (:meth:`Particles.to_numpy`:
  version 5, the paper's codes or a field's float layout; files written before it hold
  versions 3 and 2) under the name ``layer<k>.<entry>``, so each layer keeps its own precision
  and a re-rendered layer equals the sampled one bit for bit. As in a single record's file, the
  0-d entries (``layer<k>.frame``, ...) are gathered in one ``scalars`` entry
  (:mod:`weathergen.io.npz`), ``format_version`` excepted.

A single preset's record keeps its own format (version 5; 1 to 3 are still read): one layer
costs no byte more.
:func:`load_particles` reads either.
"""

from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import numpy as np
import torch

from ...errors import FormatError
from ...io.atomic import atomic_write_bytes
from ...io.npz import npz_bytes
from .particles import (LAYERED_FORMAT_VERSION, TENSOR_FIELDS, VERSION_ENTRIES, Particles,
                        read_particle_arrays)

#: The most layers one record holds (the per-particle layer index is stored as uint8).
MAX_LAYERS = 255


def layer_seed(seed: int, name: str) -> int:
    """The 63-bit seed of layer ``name`` drawn with ``seed`` (a pair's, or a field's scene seed)."""
    digest = hashlib.sha256(f"weathergen-layer:{int(seed)}:{name}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def _layer_prefix(k: int) -> str:
    return f"layer{k}."


@dataclass(frozen=True)
class LayeredParticles:
    """The particles of one frame pair under a combined preset: one record per layer.

    Attributes:
        layers: each layer's :class:`Particles` record (its own settings, and optics for a
            field layer), in the combined preset's order.
        names: each layer's name (its preset's), distinct.
    Shape: layer ``k`` holds ``counts[k]`` particles; ``N = sum(counts)`` in all.
    """

    layers: tuple[Particles, ...]
    names: tuple[str, ...]

    def __post_init__(self):
        if not isinstance(self.layers, tuple) or not isinstance(self.names, tuple):
            raise TypeError("layers and names must be tuples")
        if not self.layers or len(self.layers) != len(self.names):
            raise ValueError(f"one name per layer: {len(self.layers)} layers, "
                             f"{len(self.names)} names")
        if len(self.layers) > MAX_LAYERS:
            raise ValueError(f"at most {MAX_LAYERS} layers, got {len(self.layers)}")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"layer names must differ, got {', '.join(self.names)}")
        frames = sorted({r.frame for r in self.layers})
        if len(frames) > 1:
            raise ValueError(f"the layers live in different reference frames ({', '.join(frames)})")

    # -- shape ---------------------------------------------------------------------------------
    @property
    def counts(self) -> tuple[int, ...]:
        return tuple(r.count for r in self.layers)

    @property
    def count(self) -> int:
        return sum(self.counts)

    def __len__(self) -> int:
        return self.count

    @property
    def frame(self) -> str:
        return self.layers[0].frame

    @property
    def device(self) -> torch.device:
        return self.layers[0].device

    def layer_index(self) -> torch.Tensor:
        """The layer of every particle, layer after layer. Shape: (N,) int64."""
        return torch.repeat_interleave(torch.arange(len(self.layers), device=self.device),
                                       torch.tensor(self.counts, device=self.device))

    def concat(self, name: str) -> torch.Tensor:
        """One per-particle field (``position``, ``offset1``, ...) of every layer, layer after
        layer. Shape: (N, ...). ``template`` values index each layer's own library."""
        if name not in TENSOR_FIELDS:
            raise KeyError(f"no per-particle field {name!r} (fields: {', '.join(TENSOR_FIELDS)})")
        return torch.cat([getattr(r, name) for r in self.layers])

    # -- layers --------------------------------------------------------------------------------
    def index_of(self, which: Union[int, str]) -> int:
        """A layer's position, from its position or its name (KeyError for neither)."""
        if isinstance(which, str):
            if which not in self.names:
                raise KeyError(f"no layer {which!r} (layers: {', '.join(self.names)})")
            return self.names.index(which)
        if not -len(self.layers) <= which < len(self.layers):
            raise KeyError(f"no layer {which} ({len(self.layers)} layers)")
        return which % len(self.layers)

    def layer(self, which: Union[int, str]) -> Particles:
        """One layer's record, by position or name."""
        return self.layers[self.index_of(which)]

    def replace_layer(self, which: Union[int, str], record: Particles) -> "LayeredParticles":
        """A copy with one layer's record replaced (e.g. by one whose offsets require grad)."""
        k = self.index_of(which)
        return dataclasses.replace(self, layers=self.layers[:k] + (record,) + self.layers[k + 1:])

    def for_compat(self, compat: str) -> "LayeredParticles":
        """Combined weather as drawn under ``compat``: as it is (the research code has none; its
        layers keep weathergen's blending, see :meth:`Particles.for_compat`)."""
        return self

    def to(self, device=None, dtype=None) -> "LayeredParticles":
        """A copy with every layer on ``device``; float fields cast to ``dtype`` when given."""
        return dataclasses.replace(self, layers=tuple(r.to(device, dtype) for r in self.layers))

    def quantized(self) -> "LayeredParticles":
        """Every layer rounded to its own storage precision (idempotent)."""
        return dataclasses.replace(self, layers=tuple(r.quantized() for r in self.layers))

    # -- storage -------------------------------------------------------------------------------
    def to_numpy(self) -> dict[str, np.ndarray]:
        """The ``.npz`` content (format version 4, see the module doc)."""
        arrays: dict[str, np.ndarray] = {
            "format_version": np.array(LAYERED_FORMAT_VERSION, np.int32),
            "layer_names": np.array(self.names),
            "layer_counts": np.array(self.counts, np.int64),
            "layer": np.repeat(np.arange(len(self.layers), dtype=np.uint8), self.counts),
        }
        for k, record in enumerate(self.layers):
            for key, value in record.to_numpy().items():
                arrays[_layer_prefix(k) + key] = value
        return arrays

    def save(self, path: str | Path) -> Path:
        """Write a compressed ``.npz`` (readable with ``numpy.load``, no pickles), atomically."""
        return atomic_write_bytes(path, npz_bytes(self.to_numpy(), keep=VERSION_ENTRIES))

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], path: str | Path = "<arrays>",
                    device=None) -> "LayeredParticles":
        """The layers stored as ``arrays`` (:meth:`to_numpy`, or a file's entries); FormatError
        names ``path`` and the layer on any problem."""
        path = Path(path)
        version = arrays.get("format_version")
        if version is None or int(version) != LAYERED_FORMAT_VERSION:
            found = "none" if version is None else int(version)
            raise FormatError(path, f"particle format version {found}, not the layered format "
                                    f"{LAYERED_FORMAT_VERSION} of a combined preset")
        for key in ("layer_names", "layer_counts", "layer"):
            if key not in arrays:
                raise FormatError(path, f"layered particle file without '{key}'")
        names = tuple(str(n) for n in np.atleast_1d(arrays["layer_names"]))
        counts = np.atleast_1d(arrays["layer_counts"])
        if len(counts) != len(names) or counts.dtype.kind not in "iu" or (counts < 0).any():
            raise FormatError(path, f"'layer_counts' {counts.tolist()} does not fit "
                                    f"{len(names)} layer names")
        layer = arrays["layer"]
        want = np.repeat(np.arange(len(names)), counts)
        if layer.shape != want.shape or not np.array_equal(layer, want):
            raise FormatError(path, "'layer' is not the layer of every particle, layer after layer "
                                    f"({', '.join(f'{n}: {c}' for n, c in zip(names, counts))})")
        records = []
        for k, (name, count) in enumerate(zip(names, counts)):
            try:
                record = Particles.from_arrays(layer_arrays(arrays, k), path, device)
            except FormatError as exc:
                raise FormatError(path, f"layer {k} ({name}): {exc.problem}") from None
            if record.count != int(count):
                raise FormatError(path, f"layer {k} ({name}) holds {record.count} particles, "
                                        f"'layer_counts' says {int(count)}")
            records.append(record)
        try:
            return cls(tuple(records), names)
        except ValueError as exc:
            raise FormatError(path, str(exc)) from None

    @classmethod
    def load(cls, path: str | Path, device=None) -> "LayeredParticles":
        """Read layers written by :meth:`save`; FormatError names the file on any problem."""
        return cls.from_arrays(read_particle_arrays(path), path, device)


def layer_arrays(arrays: dict[str, np.ndarray], k: int) -> dict[str, np.ndarray]:
    """The entries of layer ``k`` of a layered file's ``arrays``, as a single record's file."""
    prefix = _layer_prefix(k)
    return {key[len(prefix):]: v for key, v in arrays.items() if key.startswith(prefix)}


def load_particles(path: str | Path, device=None) -> Union[Particles, LayeredParticles]:
    """A particle file of either kind: a single preset's record or a combined preset's layers."""
    arrays = read_particle_arrays(path)
    version = arrays.get("format_version")
    if version is not None and int(version) == LAYERED_FORMAT_VERSION:
        return LayeredParticles.from_arrays(arrays, path, device)
    return Particles.from_arrays(arrays, path, device)
