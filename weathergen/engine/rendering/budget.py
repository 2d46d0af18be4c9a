"""How much memory drawing a pair's weather takes, estimated before anything is drawn.

A preset value that is plausible on its own can still ask for more memory than the machine has (a
dense field with a far ``far`` on a large frame, a paper preset with a huge count and size): the
run would be killed by the operating system, or fail deep in an allocation. The render job asks
:func:`estimate_pair_memory` first and refuses a pair whose estimate does not fit, naming the
estimate and the preset keys that lower it most.

The estimate counts what the memory grows with (measured on the CPU, float32; see
``docs/engine.md``, "Memory"):

- the particles drawn: a weather field's expected number in view, ``density`` times the volume of
  the view frustum widened by the largest stamp, between ``near`` and ``far``, and where the scene
  lies farther (the fraction of pixels deeper than each depth, from the pair's depth maps); a paper
  preset's count for the frame (:func:`~weathergen.engine.weather.presets.frame_scaling`);
- their blur samples (``blur_samples`` where a streak is drawn) and stamp pixels (a stamp's side
  in pixels squared, an eighth of the side for stamps drawn on a coarser grid);
- a field's culling, which tests every particle of the tiles that meet the widened view volume up
  to ``far`` before the scene is consulted;
- the frames themselves (images, depth, sums, opacities).

It is meant as an upper estimate within a small factor, not an exact count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from ...errors import ConfigError
from ...memory import BUDGET_VARIABLE, Available, available_memory, human_bytes
from ..weather.presets import CombinedPreset, FieldPreset, Preset, frame_scaling
from .stamps import COARSE_MAX_LEVEL, COARSE_SIDE
from ..views import MAX_DEFOCUS

#: Bytes of every draw: the template atlas, its mip levels, tables.
BYTES_FIXED = 16 << 20
#: Bytes per pixel of the frame pair: images, depth maps, sums and opacities of both frames.
BYTES_PER_PIXEL = 320
#: Bytes per particle drawn in a pair (its record, looks, tracks and small stamp, both views).
BYTES_PER_PARTICLE = 10_000
#: Bytes per blur sample beyond the first (an instance of a particle along its streak).
BYTES_PER_SAMPLE = 900
#: Bytes per stamp pixel.
BYTES_PER_STAMP_PIXEL = 32
#: Bytes per particle that a field's culling tests.
BYTES_PER_TESTED = 400
#: Depth steps of the estimate's integrals over depth.
DEPTH_STEPS = 64
#: Window sides (powers of two) of the depth maps' farthest depths that decide occlusion.
WINDOW_LEVELS = 10
#: At most about this many depths of each map (and window side) are looked at.
SAMPLED_DEPTHS = 1 << 14


@dataclass(frozen=True)
class MemoryEstimate:
    """The estimated peak memory of drawing one pair (bytes) and what it is made of.

    ``particles``: drawn (expected); ``samples``: blur samples of all of them; ``stamp_pixels``;
    ``tested``: particles a field's culling tests; ``keys``: the preset keys that lower the
    estimate most, as ``"key (now VALUE)"``, the heaviest layer's for a combined preset
    (``layer`` names it).
    """

    bytes: int
    particles: int
    samples: int
    stamp_pixels: int
    tested: int
    keys: tuple
    layer: str = ""


def estimate_pair_memory(height: int, width: int, intrinsics: torch.Tensor,
                         depths: tuple[torch.Tensor, ...], preset) -> MemoryEstimate:
    """The memory drawing a pair of ``height`` x ``width`` frames with ``preset`` (of either
    model, or combined) takes, estimated from the camera (``intrinsics`` (3, 3)) and the scene's
    depth (``depths``: the pair's depth maps, each (1, H, W) or (H, W), scene units)."""
    f = float(torch.sqrt(intrinsics[0, 0].double() * intrinsics[1, 1].double()))
    deeper = _deeper_fraction(depths)
    layers = preset.layers if isinstance(preset, CombinedPreset) else (preset,)
    parts = [(_field_layer(p, height, width, f, deeper) if isinstance(p, FieldPreset)
              else _paper_layer(p, height, width)) for p in layers]
    heaviest = max(range(len(parts)), key=lambda i: parts[i][0])
    drawn = sum(p[0] for p in parts)
    total = BYTES_FIXED + BYTES_PER_PIXEL * height * width + drawn
    return MemoryEstimate(
        bytes=int(total), particles=int(sum(p[1] for p in parts)),
        samples=int(sum(p[2] for p in parts)), stamp_pixels=int(sum(p[3] for p in parts)),
        tested=int(sum(p[4] for p in parts)), keys=parts[heaviest][5],
        layer=layers[heaviest].name if len(layers) > 1 else "")


def _deeper_fraction(depths):
    """``fraction(z, side)``: the share of places where a stamp of ``side`` pixels at depth ``z``
    is drawn, as the culling decides it: where the farthest scene depth under the stamp (a
    window of about its side, in either frame) lies deeper than ``z``."""
    levels = []                                   # (window side, sorted farthest depths)
    pooled = [d.reshape(1, 1, *d.shape[-2:]).float().cpu() for d in depths]
    for level in range(WINDOW_LEVELS):
        if level:
            pooled = [F.max_pool2d(x, 2, 2, ceil_mode=True) for x in pooled]
        side = 2 ** level
        flat = [x.reshape(-1) for x in pooled]     # a sample of the largest: a share is enough
        flat = [x[::max(1, x.numel() // SAMPLED_DEPTHS)] for x in flat]
        levels.append((side, [torch.sort(x).values for x in flat]))

    def fraction(z: float, side: float) -> float:
        maps = next((m for s, m in reversed(levels) if s <= max(side, 1.0)), levels[0][1])
        at = torch.tensor([z], dtype=torch.float32)
        return max(1.0 - float(torch.searchsorted(d, at, right=True)) / d.numel() for d in maps)
    return fraction


def _stored_pixels(side: float) -> float:
    """Pixels a stamp of ``side`` pixels takes: its side squared, on a coarser grid (up to
    2**COARSE_MAX_LEVEL times) from :data:`~weathergen.engine.rendering.stamps.COARSE_SIDE` on."""
    if side >= COARSE_SIDE:
        side = side / 2 ** COARSE_MAX_LEVEL
    return side * side


def _bytes(particles: float, samples: float, stamp_pixels: float, tested: float) -> float:
    """The peak: a field's culling is over (its memory freed) before the particles are drawn."""
    drawing = (BYTES_PER_PARTICLE * particles + BYTES_PER_SAMPLE * max(0.0, samples - particles)
               + BYTES_PER_STAMP_PIXEL * stamp_pixels)
    return max(drawing, BYTES_PER_TESTED * tested)


def _field_layer(p: FieldPreset, height: int, width: int, f: float, deeper) -> tuple:
    """``(bytes, particles, samples, stamp pixels, tested, keys)`` of a field layer."""
    d = p.diameter * (1 + p.diameter_jitter)          # the largest: it sets the widening
    margin = 0.5 * f * d / p.near + MAX_DEFOCUS + 2   # pixels, as the culling widens the view
    mean_d = p.diameter
    particles = stamp_pixels = 0.0
    zs = [p.near * (p.far / p.near) ** ((i + 0.5) / DEPTH_STEPS) for i in range(DEPTH_STEPS)]
    edges = [p.near * (p.far / p.near) ** (i / DEPTH_STEPS) for i in range(DEPTH_STEPS + 1)]
    for z, a, b in zip(zs, edges[:-1], edges[1:]):
        side = f * mean_d / z + 2                     # a particle's stamp, pixels
        area = (width + side) * (height + side) * (z / f) ** 2   # whose stamp meets the frame
        n = p.density * area * (b - a) * deeper(z, side)
        particles += n
        stamp_pixels += n * _stored_pixels(side)
    samples = particles * (p.blur_samples if p.exposure > 0 else 1)
    tested = p.density * _frustum_volume(width + 2 * margin, height + 2 * margin, f,
                                         p.near, p.far, 0.25 * math.sqrt(3) * p.tile)
    keys = _largest(particles, samples, stamp_pixels, tested,
                    {"particles": ("density", "far"), "samples": ("blur_samples", "exposure"),
                     "stamps": ("diameter",), "tested": ("diameter", "near", "far")}, p)
    return _bytes(particles, samples, stamp_pixels, tested), particles, samples, stamp_pixels, \
        tested, keys


def _frustum_volume(width: float, height: float, f: float, near: float, far: float,
                    pad: float) -> float:
    """Volume of a view frustum of ``width`` x ``height`` pixels at focal ``f`` between ``near``
    and ``far``, each side pushed out by ``pad`` (scene units)."""
    a, b = max(0.0, near - pad), far + pad
    w, h = width / f, height / f

    def antiderivative(z):         # of (w z + 2 pad)(h z + 2 pad)
        return w * h * z ** 3 / 3 + (w + h) * pad * z * z + 4 * pad * pad * z
    return antiderivative(b) - antiderivative(a)


def _paper_layer(p: Preset, height: int, width: int) -> tuple:
    """``(bytes, particles, samples, stamp pixels, tested, keys)`` of a paper layer: its count
    for the frame, each particle's stamp at a depth drawn as a frustum fills the sampling box."""
    scaling = frame_scaling(p, height, width)
    z0, z1 = max(p.volume_z[0], 1e-3), max(p.volume_z[1], 2e-3)
    zs = [z0 + (z1 - z0) * (i + 0.5) / DEPTH_STEPS for i in range(DEPTH_STEPS)]
    weights = [z * z for z in zs]                     # a frustum's cross-section grows as z^2
    mean_pixels = sum(w * _stored_pixels(scaling.size * min(1.0, 1.0 / (z * p.depth_decay)) + 2)
                      for w, z in zip(weights, zs)) / sum(weights)
    particles = float(scaling.count)
    samples = particles * p.blur_sample_count
    stamp_pixels = particles * mean_pixels
    keys = _largest(particles, samples, stamp_pixels, 0.0,
                    {"particles": ("count",), "samples": ("blur_samples",),
                     "stamps": ("size",), "tested": ()}, p)
    return _bytes(particles, samples, stamp_pixels, 0.0), particles, samples, stamp_pixels, \
        0.0, keys


def _largest(particles, samples, stamp_pixels, tested, keys: dict, preset) -> tuple:
    """The keys of the term that weighs most, as ``"key (now VALUE)"``."""
    terms = {"particles": BYTES_PER_PARTICLE * particles,
             "samples": BYTES_PER_SAMPLE * max(0.0, samples - particles),
             "stamps": BYTES_PER_STAMP_PIXEL * stamp_pixels,
             "tested": BYTES_PER_TESTED * tested}
    name = max(terms, key=terms.get)
    return tuple(f"{k} (now {getattr(preset, k):g})" for k in keys[name])


def room_on(device) -> Optional[Available]:
    """What drawing on ``device`` may still allocate: a budget set in the environment
    (:data:`~weathergen.memory.BUDGET_VARIABLE`), else on a CUDA device its free memory, else
    the host's available memory (:func:`~weathergen.memory.available_memory`); None where
    nothing says."""
    device = torch.device(device)
    budget = available_memory()
    if device.type == "cuda" and (budget is None or budget.source != BUDGET_VARIABLE):
        free, _ = torch.cuda.mem_get_info(device)
        return Available(int(free), f"free memory of {device}")
    return budget


def check_pair_memory(pair, preset, device="cpu", share: int = 1) -> Optional[MemoryEstimate]:
    """Refuse a pair whose drawing would not fit: ConfigError saying the estimate
    (:func:`estimate_pair_memory`), the room (:func:`room_on`, divided among ``share`` pairs drawn
    at the same time: workers, a batch) and the preset keys to lower. Returns the estimate (None
    for a pair without a camera or depth, which drawing refuses in its own words)."""
    if pair.intrinsics is None or pair.depth1 is None or pair.depth2 is None:
        return None
    estimate = estimate_pair_memory(*pair.size, pair.intrinsics, (pair.depth1, pair.depth2),
                                    preset)
    room = room_on(device)
    if room is None or estimate.bytes <= room.bytes // max(1, share):
        return estimate
    shared = f", shared by {share} pairs drawn at once" if share > 1 else ""
    layer = f" of layer {estimate.layer}" if estimate.layer else ""
    keys = " or ".join(estimate.keys)
    raise ConfigError(
        f"drawing this pair needs about {human_bytes(estimate.bytes)} ({estimate.particles:,} "
        f"particles in view{f', {estimate.tested:,} tested' if estimate.tested else ''}), more "
        f"than the {human_bytes(room.bytes // max(1, share))} available ({room.source}{shared}); "
        f"lower the preset key{'s' if len(estimate.keys) > 1 else ''} {keys}{layer}")
