"""The particle record: everything that determines how one frame pair's weather is rendered.

A :class:`Particles` record is data, not code: sampling makes it, the renderer reads it, the attack
optimises its offsets, colours and transparencies, and :meth:`Particles.save` stores it as a small
``.npz`` that numpy alone can read. No rasterised template is stored, only indices into a
template library and the per-particle scale, rotation and defocus radius.

Geometry of particle ``j`` (``P`` position, ``M`` motion, ``δ1``/``δ2`` the offsets, all in the
record's reference ``frame``)::

    camera-1 position  X1 = cam1_from_ref · (P + δ1)
    camera-2 position  X2 = cam2_from_ref · (P + δ1 + M + δ2)

With ``frame == "world"`` the reference is the dataset's world (``cam1_from_ref`` is the pair's
``cam1_from_world``), so that particles can persist over a whole sequence. With
``frame == "camera1"`` (datasets without absolute poses) the reference is camera 1:
``cam1_from_ref`` is the identity and ``cam2_from_ref`` is ``cam2_from_cam1``. This equals the
paper's ``T_rel (p1 + δ1) + m + δ2`` with ``m`` and ``δ2`` expressed in the reference frame.

Appearance: a record sampled by the paper's model (``optics is None``) carries its footprint
(``scale``), defocus radius and transparency fixed at sampling. A record sampled from a weather
field (:mod:`weathergen.engine.sampling.field`) carries :class:`FieldOptics`: its ``scale`` is then the
particle's diameter in scene units and ``transparency`` its base θ, and footprint, defocus and
depth fade are computed for every frame from that frame's own depth of the particle
(:mod:`weathergen.engine.rendering.tracks`).

Stored stamps: a record may carry each particle's own stamp (``stamps``, (N, S, S): the alpha
image it is drawn with, as the paper's research code stores its particles' flakes, see
:mod:`weathergen.engine.sampling.published`); its ``template``, ``scale``, ``rotation`` and ``defocus`` are
then not used, and the particles are drawn with the record's own number of blur samples. Such a
record is kept exactly: its file has the float layout with every float field in float32 (no
rounding: :meth:`Particles.quantized` only detaches it), and every stamp: the bounding box of its
non-zero pixels (``stamp_boxes`` (N, 4) uint16: top, left, height, width), those pixels
(``stamp_pixels``, float32, one box after the other, row-major) and the side (``stamp_side``).

Storage precision of the paper's records: positions and motions as codes on a per-record linear
grid (``lo + code * step`` per axis, the grid spanning the record's values; 15 bits for
positions: a sampling box of 10 units gets steps of 3e-4 units; 10 bits for motions); colours as
8-bit codes; rotations in 256 steps of a turn; scales, offsets and transparencies float16;
template indices uint16; defocus radii uint8. Field records keep float32 positions, motions and
scales (a field's positions are exact multiples of its grid quantum, so that a frame is the same
image in every pair that holds it) and float16 offsets, colours, transparencies and rotations,
plus the ``optics`` entry and, for a field with an atmosphere (:mod:`weathergen.engine.weather.atmosphere`),
the ``atmosphere`` entry (JSON) and, for an explicit density lattice, ``atmosphere_density``
(float16). Sampling returns a record already rounded to these precisions
(:meth:`Particles.quantized`, idempotent), so rendering the in-memory record and rendering the
reloaded file give identical bytes.

File format versions (every one is still read):

- 5 (written now for a single record): the 0-d entries (reference frame, render settings, ...)
  gathered in one ``scalars`` entry (:mod:`weathergen.io.npz`; ``format_version`` stays an entry
  of its own). Paper records: the codes above, the three 10-bit motion codes of a particle packed
  into one uint32 (``x << 20 | y << 10 | z``, shape (N,)). Field records (with ``optics``): the
  float layout of version 2.
- 4: the layers of a combined preset, each a single record's entries under ``layer<k>.``
  (:mod:`weathergen.engine.records.layered`; read with ``LayeredParticles.load`` or ``load_particles``).
- 3: paper records, the codes above with motion codes as uint16 (N, 3); one entry per 0-d value.
- 2: field records, the float layout plus ``optics``.
- 1: the float layout of version 2 without optics.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ...errors import FormatError
from ...io.atomic import atomic_write_bytes
from ...io.npz import npz_bytes, read_npz
from ..weather.atmosphere import Atmosphere
from ..weather.optics import FieldOptics
from .settings import RenderSettings

#: Single records are written as version 5 (see the module doc).
FORMAT_VERSION = 5
#: Files of a combined preset's layers (:mod:`weathergen.engine.records.layered`) are version 4.
LAYERED_FORMAT_VERSION = 4
READABLE_VERSIONS = (1, 2, 3, 5)
#: Versions whose paper records store codes (grids, 8-bit colours and rotations).
_CODED_VERSIONS = (3, 5)
#: Entries a particle file keeps out of the gathered ``scalars`` (a reader must find them).
VERSION_ENTRIES = ("format_version", "metadata_version")
REFERENCE_FRAMES = ("world", "camera1")

# Per-particle tensor fields: storage dtype and trailing shape.
_TENSOR_FIELDS = {
    "position": (np.float32, (3,)),
    "motion": (np.float32, (3,)),
    "offset1": (np.float16, (3,)),
    "offset2": (np.float16, (3,)),
    "color": (np.float16, (3,)),
    "transparency": (np.float16, ()),
    "template": (np.uint16, ()),
    "rotation": (np.float16, ()),
    "scale": (np.float32, ()),
    "defocus": (np.uint8, ()),
}
_INTEGER_FIELDS = ("template", "defocus")
# Format version 3 stores some fields as codes (see the module doc); the rest as in version 1.
_GRID_FIELDS = ("position", "motion")                     # uint16 codes + "<name>_grid" (2, 3)
_CODED_DTYPES = {"color": np.uint8, "rotation": np.uint8, "scale": np.float16,
              **{name: np.uint16 for name in _GRID_FIELDS}}
# Grid levels: 15 bits for positions; 10 bits for motions (frame-to-frame displacements
# spread over a much smaller range: rain's ±10 % of 0.2 units gives steps of 4e-5 units).
_GRID_LEVELS = {"position": 32767, "motion": 1023}
_ROTATION_STEPS = 256


def _grid(values: torch.Tensor, levels: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Codes 0..levels of (N, 3) values on a per-axis grid spanning them: (codes (N, 3) int64,
    lo (3,) float64, step (3,) float64). lo and lo + levels step are the (float32) extremes, so
    decoding and encoding again gives the same codes."""
    v = values.detach().cpu().to(torch.float32).to(torch.float64)
    if v.shape[0] == 0:
        zero = torch.zeros(v.shape[1:], dtype=torch.float64)
        return torch.zeros(v.shape, dtype=torch.int64), zero, zero.clone()
    lo, hi = v.min(0).values, v.max(0).values
    step = (hi - lo) / levels
    safe = torch.where(step > 0, step, torch.ones_like(step))
    codes = torch.round((v - lo) / safe).clamp(0, levels).to(torch.int64)
    return codes, lo, step


def _ungrid(codes: torch.Tensor, lo: torch.Tensor, step: torch.Tensor) -> torch.Tensor:
    """float32 values of grid codes. Shape: (N, 3), (3,), (3,) -> (N, 3)."""
    return (lo + codes.to(torch.float64) * step).to(torch.float32)


def _pack_motion(codes: np.ndarray) -> np.ndarray:
    """Three 10-bit motion codes per particle in one uint32. Shape: (N, 3) -> (N,)."""
    c = codes.astype(np.uint32)
    return (c[:, 0] << 20) | (c[:, 1] << 10) | c[:, 2]


def _unpack_motion(words: np.ndarray) -> np.ndarray:
    """The codes :func:`_pack_motion` packed. Shape: (N,) -> (N, 3) int64."""
    w = words.astype(np.int64)
    return np.stack([(w >> 20) & 1023, (w >> 10) & 1023, w & 1023], axis=-1)


def quantize_field(name: str, t: torch.Tensor) -> torch.Tensor:
    """One field rounded to its storage precision, float32 (int64 for integer fields), on the
    CPU."""
    t = t.detach().cpu()
    if name in _INTEGER_FIELDS:
        return t.to(torch.int64)
    if name in _GRID_FIELDS:
        return _ungrid(*_grid(t, _GRID_LEVELS[name]))
    if name == "color":
        return (torch.round(t.double().clamp(0, 1) * 255) / 255).to(torch.float32)
    if name == "rotation":
        turn = torch.remainder(torch.round(t.double() / (2 * np.pi) * _ROTATION_STEPS),
                               _ROTATION_STEPS)
        return (turn * (2 * np.pi / _ROTATION_STEPS)).to(torch.float32)
    return t.to(torch.float16).to(torch.float32)

#: The names of the per-particle tensors of a record.
TENSOR_FIELDS = tuple(_TENSOR_FIELDS)


@dataclass
class Particles:
    """Per-particle parameters of one frame pair (N particles) and the render settings they need
    (``settings``, a :class:`~weathergen.engine.RenderSettings`).

    Shape:
        position: (N, 3) scene units, in ``frame`` coordinates (world or camera 1).
        motion: (N, 3) frame-to-frame displacement, scene units, ``frame`` axes.
        offset1, offset2: (N, 3) δ1 (before the motion) and δ2 (after it), scene units,
            ``frame`` axes; zero after sampling, optimised by the attack.
        color: (N, 3) RGB in [0, 1].
        transparency: (N,) θ, the alpha scale of the template (>= 0; may exceed 1 for glows).
        template: (N,) int64 index into the template library named by ``settings.templates``.
        rotation: (N,) radians, counter-clockwise on screen.
        scale: (N,) image pixels per template pixel, fixed at sampling; with ``optics``: the
            particle's diameter in scene units.
        defocus: (N,) int64 disc-blur radius in pixels (0 or 1: no blur); 0 with ``optics``.
        stamps: None, or (N, S, S) float, S odd: each particle's own stamp (alpha in [0, 1],
            drawn centred on the particle at its native pixels; see the module doc).
    Float fields are float32 (or the dtype the caller chose, e.g. float64 for gradcheck).
    """

    position: torch.Tensor
    motion: torch.Tensor
    offset1: torch.Tensor
    offset2: torch.Tensor
    color: torch.Tensor
    transparency: torch.Tensor
    template: torch.Tensor
    rotation: torch.Tensor
    scale: torch.Tensor
    defocus: torch.Tensor
    frame: str = "world"
    settings: RenderSettings = RenderSettings()
    optics: Optional[FieldOptics] = None
    atmosphere: Optional[Atmosphere] = None
    stamps: Optional[torch.Tensor] = None

    @property
    def count(self) -> int:
        return int(self.position.shape[0])

    def __len__(self) -> int:
        return self.count

    @property
    def device(self) -> torch.device:
        return self.position.device

    def replace(self, **changes) -> "Particles":
        """A copy with some fields replaced (e.g. an offset tensor that requires grad)."""
        return dataclasses.replace(self, **changes)

    def for_compat(self, compat: str) -> "Particles":
        """The record as drawn under ``compat`` (``paper`` or ``reference``): under
        ``reference`` an α-blended, motion-blurred record's blur samples are blended one after
        another and its stamps made as the research code does (:meth:`RenderSettings.
        for_compat`), under ``paper`` all at once, weathergen's stamps; the record itself where
        that changes nothing."""
        settings = self.settings.for_compat(compat)
        return self if settings == self.settings else self.replace(settings=settings)

    def to(self, device=None, dtype=None) -> "Particles":
        """A copy with tensors on ``device``; float fields cast to ``dtype`` when given."""
        moved = {}
        for name in _TENSOR_FIELDS:
            t = getattr(self, name)
            if dtype is not None and t.is_floating_point():
                t = t.to(dtype)
            moved[name] = t.to(device) if device is not None else t
        if self.atmosphere is not None:
            moved["atmosphere"] = self.atmosphere.to(device, dtype)
        if self.stamps is not None:
            t = self.stamps.to(dtype) if dtype is not None else self.stamps
            moved["stamps"] = t.to(device) if device is not None else t
        return self.replace(**moved)

    def select(self, index: torch.Tensor) -> "Particles":
        """The particles picked by a boolean mask or index tensor, shape (N,)."""
        picked = {name: getattr(self, name)[index] for name in _TENSOR_FIELDS}
        if self.stamps is not None:
            picked["stamps"] = self.stamps[index.to(self.stamps.device)]
        return self.replace(**picked)

    def quantized(self) -> "Particles":
        """A detached copy with every field rounded to its storage precision (see module doc).
        Idempotent: quantizing a quantized record changes nothing."""
        if self.stamps is not None:     # stored stamps (published weather): kept exactly
            return self.replace(**{name: getattr(self, name).detach().to(
                torch.int64 if name in _INTEGER_FIELDS else torch.float32)
                for name in _TENSOR_FIELDS}, stamps=self.stamps.detach().to(torch.float32))
        if self.optics is not None:     # field records: the float layout of version 2
            out = {}
            for name, (np_dtype, _) in _TENSOR_FIELDS.items():
                t = getattr(self, name).detach()
                if name in _INTEGER_FIELDS:
                    out[name] = t.to(torch.int64)
                else:
                    storage = torch.from_numpy(np.zeros(0, np_dtype)).dtype
                    out[name] = t.to(storage).to(torch.float32)
            if self.atmosphere is not None:
                out["atmosphere"] = self.atmosphere.quantized()
            return self.replace(**out)
        return self.replace(**{name: quantize_field(name, getattr(self, name)).to(
            getattr(self, name).device) for name in _TENSOR_FIELDS})

    def metadata(self) -> dict:
        """The non-tensor fields: reference frame and render settings."""
        return {"frame": self.frame, **self.settings.to_dict()}

    # -- storage -----------------------------------------------------------------------------

    def to_numpy(self) -> dict[str, np.ndarray]:
        """The ``.npz`` content (format version 5): storage arrays plus 0-d metadata arrays."""
        if self.optics is not None or self.stamps is not None:
            return self._to_numpy_field()
        arrays: dict[str, np.ndarray] = {"format_version": np.array(FORMAT_VERSION, np.int32)}
        for name, (np_dtype, _) in _TENSOR_FIELDS.items():
            t = getattr(self, name).detach().cpu()
            if name in _GRID_FIELDS:
                codes, lo, step = _grid(t, _GRID_LEVELS[name])
                codes = codes.numpy()
                arrays[name] = _pack_motion(codes) if name == "motion" else codes.astype(np.uint16)
                arrays[f"{name}_grid"] = torch.stack((lo, step)).numpy()
            elif name == "color":
                arrays[name] = np.round(t.double().clamp(0, 1).numpy() * 255).astype(np.uint8)
            elif name == "rotation":
                turn = np.round(t.double().numpy() / (2 * np.pi) * _ROTATION_STEPS)
                arrays[name] = np.remainder(turn, _ROTATION_STEPS).astype(np.uint8)
            else:
                arrays[name] = quantize_field(name, t).numpy().astype(
                    _CODED_DTYPES.get(name, np_dtype))
        arrays["frame"] = np.array(self.frame)
        arrays.update(self.settings.to_arrays())
        return arrays

    def _to_numpy_field(self) -> dict[str, np.ndarray]:
        """Field records: float storage arrays plus the metadata and the ``optics`` entry; records
        with stored stamps: every float field float32, plus the stamps."""
        q = self.quantized()
        arrays: dict[str, np.ndarray] = {"format_version": np.array(FORMAT_VERSION, np.int32)}
        for name, (np_dtype, _) in _TENSOR_FIELDS.items():
            arrays[name] = getattr(q, name).cpu().numpy().astype(_dtype_of(name, np_dtype, q.stamps))
        arrays["frame"] = np.array(self.frame)
        arrays.update(self.settings.to_arrays())
        if self.optics is not None:
            arrays["optics"] = np.array(json.dumps(self.optics.to_dict(), sort_keys=True))
        if self.atmosphere is not None:
            arrays.update(self.atmosphere.to_arrays())
        if self.stamps is not None:
            arrays.update(stamp_arrays(self.stamps))
        return arrays

    def save(self, path: str | Path) -> Path:
        """Write a compressed ``.npz`` (readable with ``numpy.load``, no pickles), atomically."""
        return atomic_write_bytes(path, npz_bytes(self.to_numpy(), keep=VERSION_ENTRIES))

    @classmethod
    def load(cls, path: str | Path, device=None) -> "Particles":
        """Read a record written by :meth:`save` (any readable version); FormatError names the
        file on any problem."""
        return cls.from_arrays(read_particle_arrays(path), path, device)

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray], path: str | Path = "<arrays>",
                    device=None) -> "Particles":
        """The record stored as ``arrays`` (what :meth:`to_numpy` gives, or a file's entries as
        :func:`read_particle_arrays` gives them); FormatError names ``path`` on any problem."""
        path = Path(path)
        version = _readable_version(arrays, path)
        stamped = "stamp_boxes" in arrays
        field_record = ("optics" in arrays or stamped) if version == FORMAT_VERSION \
            else version in (1, 2)
        coded = version in _CODED_VERSIONS and not field_record
        fields, n = _tensor_fields(arrays, path, version, coded=coded, stamped=stamped,
                                   device=device)
        if "frame" not in arrays:
            raise FormatError(path, "missing field 'frame'")
        frame = str(arrays["frame"].item())
        if frame not in REFERENCE_FRAMES:
            raise FormatError(path, f"unknown reference frame {frame!r}")
        optics, atmosphere = None, None
        if version == 2 or (version == FORMAT_VERSION and field_record and not stamped):
            optics, atmosphere = _field_entries(arrays, path, version, device)
        stamps = read_stamp_arrays(arrays, n, path) if stamped else None
        if stamps is not None and device is not None:
            stamps = stamps.to(device)
        return cls(**fields, frame=frame, settings=RenderSettings.from_arrays(arrays, path),
                   optics=optics, atmosphere=atmosphere, stamps=stamps)


def _readable_version(arrays: dict[str, np.ndarray], path: Path) -> int:
    """The format version of a record's ``arrays``; FormatError naming ``path`` where there is
    none, where they hold layers (a combined preset's file) or a version this one cannot read."""
    version = arrays.get("format_version")
    if version is None:
        raise FormatError(path, "no format_version: not a weathergen particle file")
    version = int(version)
    if version == LAYERED_FORMAT_VERSION:
        raise FormatError(path, "holds the layers of a combined preset; read it with "
                                "LayeredParticles.load (or load_particles)")
    if version not in READABLE_VERSIONS:
        raise FormatError(path, f"particle format version {version}; this weathergen "
                                f"reads versions {', '.join(map(str, READABLE_VERSIONS))}")
    return version


def _tensor_fields(arrays: dict[str, np.ndarray], path: Path, version: int, *, coded: bool,
                   stamped: bool, device) -> tuple[dict[str, torch.Tensor], Optional[int]]:
    """Every tensor field of a record of format ``version`` from its ``arrays``, decoded where
    they are ``coded`` (the integer layout), else as float32 or int64, on ``device``, and the
    particle count N (the first field's length). FormatError naming ``path`` for a missing
    array or one of the wrong dtype or shape."""
    n = None
    fields = {}
    for name, (np_dtype, tail) in _TENSOR_FIELDS.items():
        if name not in arrays:
            raise FormatError(path, f"missing array '{name}'")
        a = arrays[name]
        if n is None:
            n = a.shape[0] if a.ndim else -1
        want, shape = _dtype_of(name, np_dtype, stamped or None), (n, *tail)
        if coded:
            want = _CODED_DTYPES.get(name, np_dtype)
            if name == "motion" and version == FORMAT_VERSION:
                want, shape = np.uint32, (n,)
        if a.dtype != want or a.shape != shape:
            raise FormatError(path, f"array '{name}' is {a.dtype} {a.shape}, expected "
                                    f"{np.dtype(want)} {shape}")
        t = torch.from_numpy(_decoded(arrays, name, version, path)) if coded else \
            torch.from_numpy(a.astype(np.int64 if name in _INTEGER_FIELDS else np.float32))
        fields[name] = t.to(device) if device is not None else t
    return fields, n


def _field_entries(arrays: dict[str, np.ndarray], path: Path, version: int, device
                   ) -> tuple[FieldOptics, Optional[Atmosphere]]:
    """A field record's ``optics`` and its atmosphere (None without one), on ``device``;
    FormatError naming ``path`` where either is missing or unreadable."""
    if "optics" not in arrays:
        raise FormatError(path, f"version {version} field record without 'optics'")
    try:
        optics = FieldOptics.from_dict(json.loads(str(arrays["optics"])))
    except (ValueError, TypeError) as exc:
        raise FormatError(path, f"unreadable 'optics' entry ({exc})") from None
    try:
        atmosphere = Atmosphere.from_arrays(arrays)
    except (ValueError, TypeError, KeyError) as exc:
        raise FormatError(path, f"unreadable 'atmosphere' entry ({exc})") from None
    if atmosphere is not None and device is not None:
        atmosphere = atmosphere.to(device)
    return optics, atmosphere


def _dtype_of(name: str, np_dtype, stamps) -> type:
    """The storage dtype of field ``name`` in the float layout: float32 for every float field of a
    record with stored stamps (kept exactly), the field's own otherwise."""
    if stamps is not None and name not in _INTEGER_FIELDS:
        return np.float32
    return np_dtype


def stamp_arrays(stamps: torch.Tensor) -> dict[str, np.ndarray]:
    """The file entries of stored stamps (see the module doc): each stamp's bounding box of
    non-zero pixels and those pixels, exactly. Shape: (N, S, S) -> entries."""
    a = stamps.detach().cpu().to(torch.float32).numpy()
    n, side = a.shape[0], a.shape[-1]
    boxes = np.zeros((n, 4), np.uint16)
    pieces = []
    for i in range(n):
        rows = np.flatnonzero(a[i].any(1))
        cols = np.flatnonzero(a[i].any(0))
        if rows.size == 0:
            continue
        top, left = rows[0], cols[0]
        height, width = rows[-1] - top + 1, cols[-1] - left + 1
        boxes[i] = (top, left, height, width)
        pieces.append(a[i, top:top + height, left:left + width].ravel())
    pixels = np.concatenate(pieces) if pieces else np.zeros(0, np.float32)
    return {"stamp_side": np.array(side, np.int32), "stamp_boxes": boxes,
            "stamp_pixels": pixels.astype(np.float32)}


def read_stamp_arrays(arrays: dict, n: int, path) -> torch.Tensor:
    """The stamps stored by :func:`stamp_arrays`; FormatError names ``path`` on any
    inconsistency. Shape: -> (N, S, S) float32."""
    side, boxes, pixels = (arrays.get(k) for k in ("stamp_side", "stamp_boxes", "stamp_pixels"))
    if side is None or pixels is None:
        raise FormatError(path, "stamp_boxes without stamp_side and stamp_pixels")
    side = int(side)
    if side < 1 or side % 2 == 0:
        raise FormatError(path, f"stamp_side must be odd and positive, got {side}")
    if boxes.dtype != np.uint16 or boxes.shape != (n, 4) or pixels.dtype != np.float32:
        raise FormatError(path, f"stamp_boxes must be uint16 ({n}, 4) and stamp_pixels float32, "
                                f"got {boxes.dtype} {boxes.shape} and {pixels.dtype}")
    top, left, height, width = boxes.astype(np.int64).T
    if np.any(top + height > side) or np.any(left + width > side):
        raise FormatError(path, "a stamp box reaches beyond the stamp")
    sizes = height * width
    if int(sizes.sum()) != pixels.size:
        raise FormatError(path, f"stamp_pixels holds {pixels.size} values, the boxes {int(sizes.sum())}")
    out = np.zeros((n, side, side), np.float32)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    for i in np.flatnonzero(sizes):
        out[i, top[i]:top[i] + height[i], left[i]:left[i] + width[i]] = \
            pixels[starts[i]:starts[i + 1]].reshape(height[i], width[i])
    return torch.from_numpy(out)


def _decoded(arrays: dict, name: str, version: int, path) -> np.ndarray:
    """The values of a coded record's array ``name`` (versions 3 and 5), float32 (int64 for
    integer fields)."""
    a = arrays[name]
    if name in _GRID_FIELDS:
        grid = arrays.get(f"{name}_grid")
        if grid is None or grid.dtype != np.float64 or grid.shape != (2, 3):
            raise FormatError(path, f"array '{name}_grid' must be float64 (2, 3)")
        codes = (_unpack_motion(a) if name == "motion" and version == FORMAT_VERSION
                 else a.astype(np.int64))
        return _ungrid(torch.from_numpy(codes), torch.from_numpy(grid[0]),
                       torch.from_numpy(grid[1])).numpy()
    if name == "color":
        return (a.astype(np.float64) / 255).astype(np.float32)
    if name == "rotation":
        return (a.astype(np.float64) * (2 * np.pi / _ROTATION_STEPS)).astype(np.float32)
    return a.astype(np.int64 if name in _INTEGER_FIELDS else np.float32)


def _coded(arrays: dict) -> bool:
    version = int(arrays.get("format_version", FORMAT_VERSION))
    return version in _CODED_VERSIONS and not (version == FORMAT_VERSION and "optics" in arrays)


def stored_as(arrays: dict, name: str) -> str:
    """How a particle file stores the array ``name``, for display: its numpy dtype, and how its
    codes decode (``"uint16 grid"``: codes on ``NAME_grid``; ``"uint8 /255"``)."""
    a = arrays[name]
    if _coded(arrays):
        if name in _GRID_FIELDS and f"{name}_grid" in arrays:
            return f"{a.dtype} grid"
        if name == "color":
            return f"{a.dtype} /255"
        if name == "rotation":
            return f"{a.dtype} 2π/{_ROTATION_STEPS}"
    return str(a.dtype)


def read_particle_arrays(path: str | Path) -> dict[str, np.ndarray]:
    """Every entry of a particle ``.npz`` file; FormatError names the file when it cannot be read."""
    path = Path(path)
    try:
        return read_npz(path)           # the gathered 0-d entries as their own arrays again
    except FileNotFoundError:
        raise FormatError(path, "particle file does not exist") from None
    except Exception as exc:  # numpy raises several types for corrupt archives
        raise FormatError(path, f"not a particle .npz file ({exc})") from None


def empty_particles(frame: str = "world", settings: RenderSettings = RenderSettings(),
                    optics: Optional[FieldOptics] = None,
                    atmosphere: Optional[Atmosphere] = None) -> Particles:
    """A record with no particles (renders to the unchanged frames, or with ``atmosphere``
    to the frames seen through it)."""
    z3 = torch.zeros(0, 3)
    z = torch.zeros(0)
    zi = torch.zeros(0, dtype=torch.int64)
    return Particles(position=z3, motion=z3.clone(), offset1=z3.clone(), offset2=z3.clone(),
                     color=z3.clone(), transparency=z, template=zi, rotation=z.clone(),
                     scale=z.clone(), defocus=zi.clone(), frame=frame, settings=settings,
                     optics=optics, atmosphere=atmosphere)


def to_atanh(xi: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """η = atanh(2ξ − 1): a value in [0, 1] to the unbounded domain the attack optimises in.

    ξ is first clamped into [eps, 1 − eps] so that η is finite; :func:`from_atanh` inverts it
    up to that clamp.
    Shape: any -> same.
    """
    return torch.atanh(2 * xi.clamp(eps, 1 - eps) - 1)


def from_atanh(eta: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """ξ = eps + (1 − 2 eps) (tanh(η) + 1) / 2: back to (0, 1), strictly inside it.

    The affine squeeze (rather than a clamp) keeps the gradient non-zero everywhere.
    Shape: any -> same.
    """
    return eps + (1 - 2 * eps) * (torch.tanh(eta) + 1) / 2
