"""The atmosphere of a weather field: extinction of light with distance (fog, mist, the veil of
rain and snow), heterogeneous, anchored in the world and differentiable.

Along the ray of a pixel, a medium of extinction coefficient ``β(x) = β₀ ρ(x)`` (per scene unit)
keeps the transmission ``t = exp(−τ)``, ``τ = ∫₀^L β(x) ds``, of the radiance ``J`` of the
surface at distance ``L`` and adds the in-scattered airlight ``A`` (Koschmieder's model)::

    I = J t + A (1 − t)

``β₀`` comes from the preset: ``−ln(0.05) / visibility`` (the meteorological optical range, the
distance at which contrast falls to 5 %) plus the extinction of its rain and snow
(:func:`rain_extinction`, :func:`snow_extinction`). ``ρ`` is a smooth density of mean 1 fixed in
the world (:func:`density_lattice`): ``ρ = 1 + h g`` with ``g`` a periodic noise in [−1, 1] and
``h`` the preset's ``heterogeneity``, interpolated trilinearly from a lattice of
``LATTICE³`` values whose structures are ``heterogeneity_scale`` wide; it drifts with the preset's
wind, and is the same at the same world point in every frame of a sequence and in both cameras of
a stereo rig. Rays end at the scene's surface, or at ``sky_distance`` for the sky and anything
farther.

The render integrates it along every ray of a view (:mod:`~weathergen.engine.rendering.transmittance`
states how, with the constants below; the error against a fine reference is bounded and tested,
see ``docs/engine.md``, "The atmosphere").

Everything is differentiable in the density lattice and the airlight (and in the particles'
positions where they are dimmed): the attack can optimise the fog itself.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

#: Contrast threshold of the meteorological optical range (WMO): ``β = −ln(0.05) / V``.
MOR_CONTRAST = 0.05
#: Terminal fall speeds (m/s) that turn a precipitation rate into a mass concentration,
#: ``C = R / (3.6 v)`` g/m³ for ``R`` in mm/h: rain drops of 1–2 mm, snow aggregates.
RAIN_FALL_SPEED = 6.0
SNOW_FALL_SPEED = 1.0
#: Density lattice: values per axis (the lattice is periodic: it repeats every
#: ``LATTICE · heterogeneity_scale / 4`` scene units).
LATTICE = 32
#: Voxels per ``heterogeneity_scale``.
VOXELS_PER_SCALE = 4
#: Pixels between the coarse rays along which a heterogeneous medium is integrated: at most
#: this many, and at most :data:`RAY_ANGLE` radians apart (``floor(f · RAY_ANGLE)`` pixels, at
#: least 1, for a focal length of ``f`` pixels).
RAY_STEP = 8
RAY_ANGLE = 1 / 64
#: Midpoint intervals per coarse ray, from the camera to ``sky_distance``.
RAY_SAMPLES = 128
#: The first interval, as a fraction of ``sky_distance``; the others grow geometrically.
FIRST_INTERVAL = 1 / 2000
#: Airlight ``auto`` when no frames are given (a field made without a pair): a light grey.
DEFAULT_AIRLIGHT = (0.8, 0.8, 0.8)
#: ``auto`` airlight: the farthest fraction of the pixels, the brightest fraction of those, and
#: how much of their colour is kept (droplets scatter every wavelength alike: the airlight is the
#: illumination's colour, nearly grey).
AIRLIGHT_FAR = 0.05
AIRLIGHT_BRIGHT = 0.25
AIRLIGHT_CHROMA = 0.25
#: The luminance quantile of all the frames' pixels below which the ``auto`` airlight is not:
#: the frames' white point.
AIRLIGHT_WHITE = 0.99
#: Rec. 709 luminance weights.
LUMINANCE = (0.2126, 0.7152, 0.0722)


# -- extinction ------------------------------------------------------------------------------

def visibility_extinction(visibility: float) -> float:
    """``β = −ln(0.05) / visibility`` per scene unit (0 for visibility 0: clear air)."""
    return -math.log(MOR_CONTRAST) / visibility if visibility > 0 else 0.0


def extinction_visibility(extinction: float) -> float:
    """The meteorological optical range of an extinction coefficient (inf for 0)."""
    return -math.log(MOR_CONTRAST) / extinction if extinction > 0 else math.inf


def rain_extinction(rate: float) -> float:
    """Extinction of rain falling at ``rate`` mm/h, per metre: ``β = 2.24 C^0.75`` km⁻¹ for the
    mass concentration ``C`` (g/m³) of a Marshall–Palmer distribution (Stoelinga and Warner 1999),
    ``C = rate / (3.6 · 6 m/s)``."""
    if rate <= 0:
        return 0.0
    return 2.24e-3 * (rate / (3.6 * RAIN_FALL_SPEED)) ** 0.75


def snow_extinction(rate: float) -> float:
    """Extinction of snow falling at ``rate`` mm/h of liquid water, per metre:
    ``β = 10.36 C^0.7776`` km⁻¹ (Stallabrass 1985, as Stoelinga and Warner 1999 use it),
    ``C = rate / (3.6 · 1 m/s)``."""
    if rate <= 0:
        return 0.0
    return 10.36e-3 * (rate / (3.6 * SNOW_FALL_SPEED)) ** 0.7776


# -- the density lattice ---------------------------------------------------------------------

def _smooth(values: torch.Tensor, passes: int) -> torch.Tensor:
    """``passes`` periodic binomial ``[1, 2, 1] / 4`` filters along each of the three axes
    (a Gaussian of variance ``passes / 2`` voxels², in fixed-order elementwise arithmetic)."""
    out = values
    for dim in range(3):
        for _ in range(passes):
            out = 0.25 * (torch.roll(out, 1, dim) + torch.roll(out, -1, dim)) + 0.5 * out
    return out


#: The noise's octaves: (binomial passes, amplitude). Standard deviations of 4, 2 and 1 voxels,
#: i.e. ``heterogeneity_scale``, a half and a quarter of it, amplitudes halving.
OCTAVES = ((32, 1.0), (8, 0.5), (2, 0.25))


def lattice_seed(seed: int) -> int:
    """The density lattice's seed, derived from the field's (the particles' own random numbers
    are not touched)."""
    digest = hashlib.sha256(f"weathergen-atmosphere:{int(seed)}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


@lru_cache(maxsize=16)
def _noise(seed: int) -> torch.Tensor:
    gen = torch.Generator(device="cpu")
    gen.manual_seed(lattice_seed(seed))
    total = torch.zeros((LATTICE,) * 3, dtype=torch.float64)
    for passes, amplitude in OCTAVES:
        white = torch.rand((LATTICE,) * 3, generator=gen, dtype=torch.float64) * 2 - 1
        smooth = _smooth(white, passes)
        total = total + amplitude * smooth / smooth.std()
    total = total - total.mean()
    return total / total.abs().max()


def density_lattice(seed: int, heterogeneity: float) -> torch.Tensor:
    """The lattice of densities ``ρ = 1 + h g`` (mean 1 over the lattice, in ``[1 − h, 1 + h]``):
    ``g`` the sum of three octaves of periodically smoothed uniform noise (:data:`OCTAVES`),
    centred and scaled to a largest magnitude of 1. Shape: -> (LATTICE,) * 3 float64, CPU."""
    return 1 + heterogeneity * _noise(int(seed))


def wrapped_lattice(lattice: torch.Tensor) -> torch.Tensor:
    """The lattice with its first slice repeated after the last along each axis (periodic
    trilinear interpolation by ``grid_sample``). Shape: (P, P, P) -> (1, 1, P+1, P+1, P+1)."""
    out = torch.cat((lattice, lattice[:1]), 0)
    out = torch.cat((out, out[:, :1]), 1)
    out = torch.cat((out, out[:, :, :1]), 2)
    return out[None, None]


def sample_lattice(lattice: torch.Tensor, voxels: torch.Tensor) -> torch.Tensor:
    """Periodic trilinear interpolation of ``lattice`` at points in voxel units (axis ``i`` of
    the lattice along reference axis ``i``). Differentiable in the lattice.
    Shape: lattice (P, P, P), voxels (..., 3) float64 -> (...) in the lattice's dtype."""
    size = lattice.shape[0]
    coords = torch.remainder(voxels, size) * (2.0 / size) - 1
    grid = coords.flip(-1).reshape(1, -1, 1, 1, 3).to(lattice.dtype)     # grid_sample: x, y, z
    out = F.grid_sample(wrapped_lattice(lattice), grid, mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out.reshape(voxels.shape[:-1])


# -- the record ------------------------------------------------------------------------------

_LATTICES: dict = {}

@dataclass
class Atmosphere:
    """The atmosphere a field record carries: what a render needs to integrate it in any view of
    the record's pair (:mod:`~weathergen.engine.rendering.transmittance`).

    Lengths in scene units (metres on metric datasets), in the record's reference frame.
    extinction: β₀ (per scene unit); heterogeneity: ``h`` in [0, 1); scale: the
    ``heterogeneity_scale`` (the lattice's voxels are ``scale / VOXELS_PER_SCALE`` wide); seed:
    the density lattice's field seed; drift (2, 3) float64: where the density field has drifted
    to (with the wind) in the pair's frames 1 and 2 (``frame · velocity / frame_rate``);
    airlight (3,) RGB in [0, 1]; sky_distance: where rays end; density: an explicit density
    lattice (LATTICE,)*3 (an attacked one), None for the seed's (or, with ``h = 0``, a uniform
    medium).
    """

    extinction: float
    airlight: torch.Tensor
    drift: torch.Tensor
    heterogeneity: float = 0.0
    scale: float = 20.0
    seed: int = 0
    sky_distance: float = 1000.0
    density: Optional[torch.Tensor] = None

    @property
    def uniform(self) -> bool:
        """True where ``ρ = 1`` everywhere (``τ = β₀ L`` exactly)."""
        return self.density is None and self.heterogeneity == 0

    @property
    def voxel(self) -> float:
        """The lattice's spacing, scene units."""
        return self.scale / VOXELS_PER_SCALE

    def replace(self, **changes) -> "Atmosphere":
        return dataclasses.replace(self, **changes)

    def lattice(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """The density lattice ρ (explicit, or the seed's, made once per process for each
        dtype and device). Shape: (LATTICE,) * 3."""
        if self.density is not None:
            return self.density.to(device=device, dtype=dtype) if device is not None \
                else self.density.to(dtype)
        key = (int(self.seed), float(self.heterogeneity), dtype, str(torch.device(device or "cpu")))
        if key not in _LATTICES:
            if len(_LATTICES) >= 32:
                _LATTICES.clear()
            _LATTICES[key] = density_lattice(self.seed, self.heterogeneity).to(
                device=device, dtype=dtype)
        return _LATTICES[key]

    def to(self, device=None, dtype=None) -> "Atmosphere":
        """A copy with the airlight (and an explicit density) on ``device`` / in ``dtype``."""
        def move(t):
            if t is None:
                return None
            t = t.to(dtype) if dtype is not None and t.is_floating_point() else t
            return t.to(device) if device is not None else t
        return self.replace(airlight=move(self.airlight), density=move(self.density),
                            drift=self.drift.to(device) if device is not None else self.drift)

    def quantized(self) -> "Atmosphere":
        """The storage precision: an explicit density as float16 values (float32), the airlight
        as float64. Idempotent."""
        density = None if self.density is None else \
            self.density.detach().to(torch.float16).to(torch.float32)
        return self.replace(airlight=self.airlight.detach().to(torch.float64),
                            drift=self.drift.detach().to(torch.float64), density=density)

    def to_dict(self) -> dict:
        """The scalars (JSON; floats round-trip exactly)."""
        return {"extinction": float(self.extinction),
                "airlight": [float(c) for c in self.airlight.detach().cpu().double().tolist()],
                "drift": [[float(c) for c in row] for row in self.drift.double().tolist()],
                "heterogeneity": float(self.heterogeneity), "scale": float(self.scale),
                "seed": int(self.seed), "sky_distance": float(self.sky_distance)}

    def to_arrays(self) -> dict[str, np.ndarray]:
        """A particle file's entries: ``atmosphere`` (JSON) and, for an explicit density,
        ``atmosphere_density`` float16 (LATTICE,) * 3."""
        out = {"atmosphere": np.array(json.dumps(self.to_dict(), sort_keys=True))}
        if self.density is not None:
            out["atmosphere_density"] = self.density.detach().cpu().numpy().astype(np.float16)
        return out

    @classmethod
    def from_arrays(cls, arrays: dict) -> Optional["Atmosphere"]:
        """The atmosphere stored in a particle file's entries (None without one). Raises
        ValueError (or KeyError, TypeError) on an unreadable entry."""
        if "atmosphere" not in arrays:
            return None
        data = json.loads(str(arrays["atmosphere"]))
        unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"unknown atmosphere keys {unknown}")
        density = arrays.get("atmosphere_density")
        if density is not None:
            if density.dtype != np.float16 or density.shape != (LATTICE,) * 3:
                raise ValueError(f"'atmosphere_density' is {density.dtype} {density.shape}, "
                                 f"expected float16 {(LATTICE,) * 3}")
            density = torch.from_numpy(density.astype(np.float32))
        airlight = torch.tensor(data["airlight"], dtype=torch.float64)
        drift = torch.tensor(data["drift"], dtype=torch.float64)
        if airlight.shape != (3,) or drift.shape != (2, 3):
            raise ValueError("airlight must be 3 numbers and drift two rows of 3")
        return cls(extinction=float(data["extinction"]), airlight=airlight, drift=drift,
                   heterogeneity=float(data.get("heterogeneity", 0.0)),
                   scale=float(data.get("scale", 20.0)), seed=int(data.get("seed", 0)),
                   sky_distance=float(data.get("sky_distance", 1000.0)), density=density)


# -- the airlight ----------------------------------------------------------------------------

def camera_rows(intrinsics: torch.Tensor) -> torch.Tensor:
    """``fx, fy, cx, cy, skew`` of intrinsics. Shape: (..., 3, 3) -> (..., 5) float64."""
    k = intrinsics.double()
    return k.reshape(*k.shape[:-2], 9)[..., [0, 4, 2, 5, 1]]


def ray_norms(camera: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``|K⁻¹ (u, v, 1)|``: scene distance per unit of camera depth along the ray through image
    point ``(u, v)``. Shape: camera (..., 5) (:func:`camera_rows`, on the points' device)
    broadcast with u, v (...) -> (...) float64."""
    fx, fy, cx, cy, skew = camera.unbind(-1)
    y = (v.double() - cy) / fy
    x = (u.double() - cx - skew * y) / fx
    return torch.sqrt(x * x + y * y + 1)


def pixel_distances(depth: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
    """Scene distance of every pixel's surface: camera-z times its ray's norm.
    Shape: depth (..., H, W), intrinsics (3, 3) -> (..., H, W) float64."""
    height, width = depth.shape[-2:]
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64, device=depth.device),
                          torch.arange(width, dtype=torch.float64, device=depth.device),
                          indexing="ij")
    return depth.double() * ray_norms(camera_rows(intrinsics).to(depth.device), u, v)


def estimate_airlight(images: Sequence[torch.Tensor], depths: Sequence[torch.Tensor],
                      intrinsics: torch.Tensor, sky_distance: float = 1000.0) -> torch.Tensor:
    """The ``auto`` airlight of some frames (both frames of a pair, so that it is the same in
    both): among the :data:`AIRLIGHT_FAR` farthest pixels of all of them (surfaces beyond
    ``sky_distance`` count as at it), the mean colour of the :data:`AIRLIGHT_BRIGHT` brightest
    (Rec. 709 luminance), its colour then reduced to :data:`AIRLIGHT_CHROMA` of itself around its
    luminance (fog and rain droplets scatter every wavelength alike: the airlight has the colour
    of the light, not the sky's blue), and brightened, where it is darker, to the frames' white
    point (the :data:`AIRLIGHT_WHITE` quantile of every pixel's luminance: without sky in view
    the farthest surfaces can be dark walls, while the air is lit as a white surface is).
    Shape: images (3, H, W), depths (1, H, W) -> (3,) float64 in [0, 1], on the CPU."""
    colours, distances = [], []
    for image, depth in zip(images, depths):
        colours.append(image.detach().double().cpu().reshape(3, -1))
        distances.append(pixel_distances(depth.detach().cpu()[0], intrinsics.cpu())
                         .clamp(max=sky_distance).reshape(-1))
    colour, distance = torch.cat(colours, 1), torch.cat(distances)
    far = max(1, int(round(AIRLIGHT_FAR * distance.numel())))
    # the farthest pixels, ties broken by position (a stable, machine-independent choice)
    order = torch.argsort(distance, descending=True, stable=True)[:far]
    candidates = colour[:, order]
    luminance = (torch.tensor(LUMINANCE, dtype=torch.float64)[:, None] * candidates).sum(0)
    bright = max(1, int(round(AIRLIGHT_BRIGHT * far)))
    chosen = torch.argsort(luminance, descending=True, stable=True)[:bright]
    mean = candidates[:, chosen].mean(1)
    weights = torch.tensor(LUMINANCE, dtype=torch.float64)
    grey = (weights * mean).sum()
    light = grey + AIRLIGHT_CHROMA * (mean - grey)
    # no darker than the frames' white point: with no sky in view the farthest surfaces may be
    # dark, while the air is lit as a white surface is
    all_luminance = (weights[:, None] * colour).sum(0)
    white = torch.sort(all_luminance).values[int(AIRLIGHT_WHITE * (all_luminance.numel() - 1))]
    if float(grey) < float(white) and float(grey) > 0:
        light = light * (white / grey)
    elif float(grey) <= 0:
        light = white.expand(3).clone()
    return light.clamp(0, 1)


# -- integration along rays ------------------------------------------------------------------

@lru_cache(maxsize=8)
def ray_nodes(sky_distance: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Distances along a ray: the ends ``s`` (M + 1,) of :data:`RAY_SAMPLES` intervals from 0 to
    ``sky_distance`` growing geometrically from ``FIRST_INTERVAL · sky_distance``, their midpoints
    and lengths (M,). float64, CPU."""
    m, first = RAY_SAMPLES, FIRST_INTERVAL
    lo, hi = 1.0, 2.0               # ratio q: first (q^M − 1) / (q − 1) = 1 (in units of sky)
    for _ in range(200):
        q = 0.5 * (lo + hi)
        if first * (q ** m - 1) / (q - 1) > 1:
            hi = q
        else:
            lo = q
    q = 0.5 * (lo + hi)
    lengths = first * q ** torch.arange(m, dtype=torch.float64)
    lengths = lengths / lengths.sum() * sky_distance
    ends = torch.cat((torch.zeros(1, dtype=torch.float64), torch.cumsum(lengths, 0)))
    ends[-1] = sky_distance
    lengths = ends[1:] - ends[:-1]
    return ends, 0.5 * (ends[1:] + ends[:-1]), lengths
