"""The differentiable particle renderer: frames and particle records in, weather frames out.

Pure functions, tensors in and tensors out, no file I/O; device-agnostic (CPU or CUDA: every
tensor follows the images' device). Four stages:

1. **Stamps** (:func:`build_stamps`, no gradient): each particle's template is rotated and scaled
   to its own footprint (``scale`` x template resolution pixels), sampled from a mip level no
   finer than twice the footprint (no aliasing for far, tiny particles), and disc-blurred by its
   defocus radius (then brightened, :func:`defocus_brighten`). A stamp is centred on a pixel.
   Particles are grouped into buckets of equal stamp side so that each bucket is one batched
   tensor operation; a far particle costs a few pixels, a near one its full size.
2. **Instances**: each particle becomes ``K`` motion-blur samples per frame, spaced evenly from its
   camera position ``X_t`` along its apparent 3D motion ``X2 − X1`` (camera-2 minus camera-1
   coordinates: its own motion and the camera's) up to ``blur_length`` times it, each with
   transparency ``θ / K``; they are projected into their camera.
3. **Splatting**: every instance's stamp is shifted by its sub-pixel position with bilinear
   weights (an (s+1) x (s+1) patch: differentiable with respect to the position), multiplied by the
   visibility ``V = 1 / (1 + exp(β (d − D)))`` against the scene depth ``D`` under each patch pixel
   and by ``θ / K``, and scatter-added (``index_add_``) into per-pixel sums ``A = Σ θ B V`` and
   ``C_c = Σ γ_c θ B V``. Instances are processed in chunks of bounded size, and the backward
   pass recomputes each chunk instead of keeping it: with or without gradients, memory is bounded
   by the chunk size (plus a few numbers per blur sample and the four accumulators), whatever the
   particles' footprints.
4. **Blending**: additive ``I + C`` or order-independent alpha ``I (1 − A) + C`` (Meshkin), then
   clamped to [0, 1]. The opacity mask is ``clamp(A, 0, 1)``.

Records sampled from a weather field (``optics`` set) look different in each frame; :func:`render`
hands them to :mod:`weathergen.engine.perframe`, which renders one view at a time with the stamps
and splat core of this module.

Gradients flow to ``offset1``, ``offset2`` (through the projected positions and the particle depth
in ``V``), ``color`` and ``transparency``; use ``beta=BETA_ATTACK`` when differentiating
through occlusion, and ``detach_occlusion=True`` for a ``V`` that passes no gradient (the
authors' research code detaches it). On CUDA, ``index_add_`` uses atomics, so results may differ in the last bits
between runs; on the CPU they are reproducible bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Union

import torch
import torch.nn.functional as F

from ..errors import ConfigError, DatasetError, ShapeError
from ..framepair import FramePair, FramePairBatch
from ..geometry import project, transform_points
from .compositing import blend, upsample
from .particles import Particles
from .presets import BLEND_MODES
from .sampling import NEAR, check_pair_for_engine, reference_transforms, resolve_device
from .templates import TemplateLibrary, load_templates

BETA_RENDER = 250.0
BETA_ATTACK = 30.0
DEFAULT_CHUNK_ELEMENTS = 1 << 21
# Stamps at least this many pixels wide (fog, large dust) are splatted on a coarser grid (the
# largest power-of-two factor up to 2**COARSE_MAX_LEVEL = 8 that keeps them >= COARSE_MIN_SIDE
# coarse pixels wide: 8 for every stamp of 128 px or more) and upsampled; see docs/engine.md for
# the accuracy. None (the ``coarse_side`` argument) renders everything exactly.
COARSE_SIDE = 128
COARSE_MIN_SIDE = 16
COARSE_MAX_LEVEL = 3
# Coarse buckets are joined while zero padding adds at most this many patch pixels per join.
MERGE_PADDING_PIXELS = 8000
#: Renders records whose looks follow each frame's depth (``optics`` set: weather fields).
#: :mod:`weathergen.engine.perframe` installs its ``render_per_frame`` here when it is imported (the
#: engine package always imports it), so that this module does not import the one built on it.
PER_FRAME_RENDERER = None


@dataclass
class RenderOutput:
    """Shape: image1, image2 (B, 3, H, W) in [0, 1]; opacity1, opacity2 (B, 1, H, W) in [0, 1];
    reached (B,) bool: which pairs' frames any instance of their record was splatted into (a
    pair that none reached has frames that do not depend on its particles)."""

    image1: torch.Tensor
    image2: torch.Tensor
    opacity1: torch.Tensor
    opacity2: torch.Tensor
    reached: Optional[torch.Tensor] = None


@dataclass
class StampBucket:
    """Stamps of one side length. Shape: stamps (n, side, side); particles (n,) int64 indices
    into the concatenation of the rendered records' particles. ``coarse`` > 0: the stamps are
    drawn on a grid ``2**coarse`` times coarser than the image (large billboards)."""

    side: int
    particles: torch.Tensor
    stamps: torch.Tensor
    coarse: int = 0


@dataclass
class StampSet:
    """All stamps of a render call, reusable while scale, rotation, template and defocus stay
    fixed (e.g. across attack steps). Shape: bucket_of, slot_of (P,) int64: each particle's bucket
    and its row in that bucket's ``stamps``."""

    buckets: list
    bucket_of: torch.Tensor
    slot_of: torch.Tensor


# -- stamps --------------------------------------------------------------------------------

def _bucket_sides(limit: int = 8193) -> torch.Tensor:
    """Allowed stamp sides: every odd size up to 15, then odd sizes ~15 % apart (at most ~30 %
    more pixels than the footprint needs, and few buckets)."""
    sides = list(range(3, 16, 2))
    while sides[-1] < limit:
        nxt = int(math.ceil(sides[-1] * 1.15))
        sides.append(nxt + 1 - nxt % 2)
    return torch.tensor(sides)


_SIDES = _bucket_sides()
_MIP_CACHE: dict = {}


def mip_pyramid(lib: TemplateLibrary, dtype: torch.dtype, device: torch.device) -> list:
    """The template library and its 2x2-averaged reductions while the side stays even and >= 4.
    Shape: list of (T, 1, R_L, R_L)."""
    key = (lib.digest, lib.name, dtype, str(device))
    if key not in _MIP_CACHE:
        level = lib.alphas.to(device=device, dtype=dtype)[:, None]
        levels = [level]
        while level.shape[-1] % 2 == 0 and level.shape[-1] >= 4:
            level = F.avg_pool2d(level, 2)
            levels.append(level)
        if len(_MIP_CACHE) > 16:
            _MIP_CACHE.clear()
        _MIP_CACHE[key] = levels
    return _MIP_CACHE[key]


def _disc_kernel(radius: int, dtype, device) -> torch.Tensor:
    """Normalised disc PSF. Shape: (1, 1, 2r+1, 2r+1)."""
    off = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    disc = ((off[:, None] ** 2 + off[None, :] ** 2) <= radius * radius).to(dtype)
    return (disc / disc.sum())[None, None]


def _disc_blur(stamp: torch.Tensor, radius: int) -> torch.Tensor:
    """Full 2D convolution with a normalised disc: (n, s, s) -> (n, s + 2r, s + 2r).

    Small cases convolve directly; large ones use an FFT in float64, whose round-off (~1e-16)
    stays invisible even after the cube-root brightening, and zero what is below 1e-12.
    """
    side = stamp.shape[-1]
    if side * side * (2 * radius + 1) ** 2 <= 1 << 18:
        # a weighted sum of shifted copies: for these small stamps far cheaper than a
        # convolution call (whose per-call set-up dominates on the CPU)
        kernel = _disc_kernel(radius, stamp.dtype, stamp.device)[0, 0]
        full = side + 2 * radius
        padded = F.pad(stamp, (2 * radius,) * 4)
        out = torch.zeros(stamp.shape[0], full, full, dtype=stamp.dtype, device=stamp.device)
        weight = float(kernel[radius, radius])      # every tap of the disc has the same weight
        for dy, dx in torch.nonzero(kernel > 0).tolist():
            out += padded[:, dy:dy + full, dx:dx + full]
        return out * weight
    full = side + 2 * radius
    kernel = _disc_kernel(radius, torch.float64, stamp.device)[0, 0]
    spec = torch.fft.rfft2(stamp.double(), s=(full, full)) * torch.fft.rfft2(kernel, s=(full, full))
    out = torch.fft.irfft2(spec, s=(full, full))
    return torch.where(out > 1e-12, out, torch.zeros_like(out)).to(stamp.dtype)


def defocus_brighten(blurred: torch.Tensor) -> torch.Tensor:
    """The depth-of-field alpha of a disc-blurred template: ``min(1, (2 b)^(1/3))``.

    The blur spreads a particle's alpha thin; doubling it and taking the cube root brings it
    back up (near, out-of-focus particles look like large soft discs rather than vanishing),
    as the paper's research code does. Shape: any -> same.
    """
    return (2 * blurred).clamp(min=0).pow(1.0 / 3.0).clamp(max=1)


def _supersampling(side: int) -> int:
    """Samples per pixel and axis for a stamp of ``side`` pixels: tiny stamps are box-filtered
    (each pixel averages 4 x 4 or 2 x 2 samples of the template and of its disc), so a far
    particle keeps the opacity its continuous footprint covers."""
    return 4 if side <= 5 else (2 if side <= 9 else 1)


#: Tolerance of the disc test in :func:`_stamp_chunk` (relative squared radius).
RIM_MARGIN = 1e-5


def _stamp_chunk(levels: list, level: int, template: torch.Tensor, rotation: torch.Tensor,
                 footprint: torch.Tensor, side: int) -> torch.Tensor:
    """Rotate and scale templates onto an integer-centred grid. Shape: -> (n, side, side)."""
    dtype, device = levels[0].dtype, levels[0].device
    h = (side - 1) // 2
    sub = _supersampling(side)
    off = torch.arange(-h, h + 1, dtype=dtype, device=device)
    if sub > 1:  # sample positions inside each pixel, pixel-major: (side * sub,)
        frac = (torch.arange(sub, dtype=dtype, device=device) + 0.5) / sub - 0.5
        off = (off[:, None] + frac[None, :]).reshape(-1)
    gy, gx = torch.meshgrid(off, off, indexing="ij")
    c = torch.cos(rotation)[:, None, None]
    s = torch.sin(rotation)[:, None, None]
    half = (footprint / 2)[:, None, None]
    # Image offset = Rot(rotation) · template offset, so sample the template at Rot(−rotation).
    xn = (c * gx + s * gy) / half
    yn = (-s * gx + c * gy) / half
    # Templates are round (see templates.py). Rim samples of even-sized footprints lie exactly on
    # the circle; the margin keeps them inside whatever the last bit of rounding (float32 or
    # float64, CPU or GPU) makes of it.
    inside = (xn * xn + yn * yn) <= 1.0 + RIM_MARGIN
    src = levels[level][template]
    out = F.grid_sample(src, torch.stack((xn, yn), -1), mode="bilinear",
                        padding_mode="zeros", align_corners=False)[:, 0] * inside
    if sub > 1:
        out = out.view(-1, side, sub, side, sub).mean((2, 4))
    return out


def stamp_geometry(footprint: torch.Tensor, defocus: torch.Tensor, resolution: int,
                   level_count: int, coarse_side: Optional[int] = COARSE_SIDE) -> tuple:
    """Each particle's stamp layout from its footprint (pixels, float64, >= 1) and defocus radius.

    Stamps at least ``coarse_side`` pixels wide (template plus defocus) go to a grid ``f = 2**L``
    times coarser (f the largest power of two up to ``2**COARSE_MAX_LEVEL`` keeping them >=
    COARSE_MIN_SIDE coarse pixels wide), footprint and radius divided by f. Returns
    ``(footprint, radius, coarse, side, sub, level)``, all (P,): the footprint on its grid, the
    disc-blur radius (0: none; radii <= 1 do not blur), the grid level L, the stamp side before
    the blur (an allowed bucket side covering every pixel the footprint's disc reaches), the
    supersampling per axis and the mip level (no finer than twice the footprint).
    """
    radius = torch.where(defocus > 1, defocus, torch.zeros_like(defocus))
    coarse = torch.zeros_like(radius)
    if coarse_side is not None:
        full = footprint + 2 * radius
        coarse = torch.where(full >= coarse_side,
                             torch.floor(torch.log2(full / COARSE_MIN_SIDE))
                             .clamp(1, COARSE_MAX_LEVEL),
                             torch.zeros_like(full)).long()
        factor = (2.0 ** coarse).to(torch.float64)
        footprint = (footprint / factor).clamp(min=1.0)
        radius = torch.where(coarse > 0, torch.floor(radius / factor + 0.5).long(), radius)
    # every pixel the footprint's disc reaches (partly covered ones are box-filtered)
    raw_side = 2 * torch.floor(footprint / 2 + 0.5).clamp(min=1).long() + 1
    sides = _SIDES.to(footprint.device)
    side = sides[torch.searchsorted(sides, raw_side)]
    sub = torch.where(side <= 5, 4, torch.where(side <= 9, 2, 1))
    level = torch.floor(torch.log2(resolution / (footprint * sub))) \
        .clamp(0, level_count - 1).long()
    return footprint, radius, coarse, side, sub, level


def build_stamps(records: Sequence[Particles], lib: TemplateLibrary, *,
                 dtype: torch.dtype = torch.float32, device=None,
                 chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
                 coarse_side: Optional[int] = COARSE_SIDE) -> StampSet:
    """Rasterise every particle's template at its footprint (no gradient; see module doc).

    Stamps at least ``coarse_side`` pixels wide (template plus defocus) are drawn on a grid
    ``f = 2**L`` times coarser (f the largest power of two up to ``2**COARSE_MAX_LEVEL``
    keeping them >= COARSE_MIN_SIDE coarse pixels wide): footprint and defocus radius divided by
    f; ``None`` disables this. Coarse stamps of similar sides share a bucket (zero-padded, see
    :func:`_merge_coarse_buckets`).
    """
    device = torch.device(device) if device is not None else records[0].device
    with torch.no_grad():
        template = torch.cat([r.template for r in records]).to(device)
        rotation = torch.cat([r.rotation for r in records]).to(device=device, dtype=dtype)
        footprint = torch.cat([r.scale for r in records]).to(device=device, dtype=torch.float64)
        footprint = (footprint * lib.resolution).clamp(min=1.0)
        defocus = torch.cat([r.defocus for r in records]).to(device)
        brighten = torch.cat([torch.full((r.count,), bool(r.settings.defocus_brighten),
                                         device=device) for r in records]) & (defocus > 1)
        if int(template.numel()) and (int(template.min()) < 0 or int(template.max()) >= lib.count):
            raise ConfigError(f"particle template index out of range for the {lib.count} "
                              f"templates of '{lib.name}'")
        levels = mip_pyramid(lib, dtype, device)
        footprint, radius, coarse, side, _, level = stamp_geometry(
            footprint, defocus, lib.resolution, len(levels), coarse_side)
        key = (((side * 64 + level) * 64 + radius) * 2 + brighten.long()) * 16 + coarse
        keys, bucket_of = torch.unique(key, return_inverse=True)
        slot_of = torch.zeros_like(bucket_of)
        buckets = []
        for b, k in enumerate(keys.tolist()):
            members = torch.nonzero(bucket_of == b).squeeze(1)
            slot_of[members] = torch.arange(members.numel(), device=device)
            lev, k = k % 16, k // 16
            bright, k = k % 2, k // 2
            r, k = k % 64, k // 64
            lvl, s = k % 64, k // 64
            per_chunk = max(1, chunk_elements // (s * s * 4 * _supersampling(s) ** 2))
            parts = []
            for start in range(0, members.numel(), per_chunk):
                m = members[start:start + per_chunk]
                stamp = _stamp_chunk(levels, lvl, template[m], rotation[m],
                                     footprint[m].to(dtype), s)
                if r > 1 or (lev and r > 0):
                    stamp = _disc_blur(stamp, r)
                if bright:
                    stamp = defocus_brighten(stamp)
                parts.append(stamp)
            buckets.append(StampBucket(side=s + 2 * r, particles=members,
                                       stamps=torch.cat(parts), coarse=lev))
        if any(bk.coarse for bk in buckets):
            buckets = _merge_coarse_buckets(buckets, bucket_of, slot_of)
    return StampSet(buckets=buckets, bucket_of=bucket_of, slot_of=slot_of)


def _merge_coarse_buckets(buckets: list, bucket_of: torch.Tensor,
                          slot_of: torch.Tensor) -> list:
    """Join coarse buckets of one level into fewer, wider ones (stamps zero-padded to the widest
    side of each group), so that the few large billboards are splatted in a few chunks: a chunk
    costs a fixed set-up, a padded pixel a little. Smallest sides first, a bucket joins the group
    before it while the padding adds at most MERGE_PADDING_PIXELS patch pixels. Updates
    ``bucket_of`` and ``slot_of`` in place; fine buckets keep their order and come first."""
    fine = [bk for bk in buckets if not bk.coarse]
    groups: list = []
    for bk in sorted((bk for bk in buckets if bk.coarse), key=lambda b: (b.coarse, b.side)):
        if groups and groups[-1][0].coarse == bk.coarse:
            n = sum(b.particles.numel() for b in groups[-1])
            side = max(b.side for b in groups[-1])
            if n * ((bk.side + 1) ** 2 - (side + 1) ** 2) <= MERGE_PADDING_PIXELS:
                groups[-1].append(bk)
                continue
        groups.append([bk])
    merged = []
    for group in groups:
        side = max(b.side for b in group)
        stamps = torch.cat([F.pad(b.stamps, ((side - b.side) // 2,) * 4) for b in group])
        merged.append(StampBucket(side=side, particles=torch.cat([b.particles for b in group]),
                                  stamps=stamps, coarse=group[0].coarse))
    out = fine + merged
    for b, bk in enumerate(out):
        bucket_of[bk.particles] = b
        slot_of[bk.particles] = torch.arange(bk.particles.numel(), device=slot_of.device)
    return out


# -- instances and splatting ----------------------------------------------------------------

def _blur_steps(record: Particles, dtype, device) -> torch.Tensor:
    """Fractions of the displacement at which blur samples sit. Shape: (K,)."""
    k = int(record.settings.blur_samples)
    if k <= 1 or record.settings.blur_length <= 0:
        return torch.zeros(1, dtype=dtype, device=device)
    return torch.linspace(0.0, float(record.settings.blur_length), k, dtype=dtype, device=device)


def _instances(records, intrinsics, cam1_from_ref, cam2_from_ref, dtype, device):
    """Projected blur samples of all records in both frames.

    Returns a dict of flat tensors (I instances): u, v (pixels), z (camera depth), theta (θ/K),
    color (I, 3), target (frame t * B + batch index), particle (global particle index).
    """
    out = {k: [] for k in ("u", "v", "z", "theta", "color", "target", "particle")}
    batch = len(records)
    first = 0
    for b, rec in enumerate(records):
        n = rec.count
        if n == 0:
            continue
        pos = rec.position.to(device=device, dtype=dtype)
        motion = rec.motion.to(device=device, dtype=dtype)
        d1 = rec.offset1.to(device=device, dtype=dtype)
        d2 = rec.offset2.to(device=device, dtype=dtype)
        steps = _blur_steps(rec, dtype, device)
        k = steps.numel()
        # Camera positions X1 = cam1 (P + δ1), X2 = cam2 (P + δ1 + M + δ2). The streak runs
        # along X2 − X1, the particle's apparent 3D motion in camera coordinates, which holds
        # its own motion and the camera's ("true motion blur respects 3D motion and camera
        # motion"); frame t's samples sit at X_t + s (X2 − X1).
        x1 = transform_points(cam1_from_ref[b], pos + d1)
        x2 = transform_points(cam2_from_ref[b], pos + d1 + motion + d2)
        streak = steps[None, :, None] * (x2 - x1)[:, None, :]            # (N, K, 3)
        theta = (rec.transparency.to(device=device, dtype=dtype) / k)[:, None].expand(n, k)
        color = rec.color.to(device=device, dtype=dtype)[:, None, :].expand(n, k, 3)
        index = (first + torch.arange(n, device=device))[:, None].expand(n, k)
        for t, x in enumerate((x1, x2)):
            pix, z = project((x[:, None, :] + streak).reshape(-1, 3), intrinsics[b])
            out["u"].append(pix[:, 0])
            out["v"].append(pix[:, 1])
            out["z"].append(z)
            out["theta"].append(theta.reshape(-1))
            out["color"].append(color.reshape(-1, 3))
            out["target"].append(torch.full((n * k,), t * batch + b, device=device,
                                            dtype=torch.long))
            out["particle"].append(index.reshape(-1))
        first += n
    if not out["u"]:
        return None
    return {key: torch.cat(v) for key, v in out.items()}


def _splat_plan(inst, stamps: StampSet, height, width, chunk_elements, coarse=0, u=None,
                v=None):
    """Which instances each chunk splats: a list of (bucket, instance indices (n,) int64), every
    chunk at most ``chunk_elements`` patch pixels. Only buckets of the given ``coarse`` level;
    ``u``, ``v`` the instances' positions on that level's grid. Instances behind the camera or
    whose patch misses the image are left out."""
    u = inst["u"] if u is None else u
    v = inst["v"] if v is None else v
    members = [b for b, bk in enumerate(stamps.buckets) if bk.coarse == coarse]
    if not members:
        return []
    device = u.device
    sides = torch.tensor([bk.side for bk in stamps.buckets], device=device)
    on_level = torch.zeros(len(stamps.buckets), dtype=torch.bool, device=device)
    on_level[members] = True
    bucket = stamps.bucket_of[inst["particle"]]
    half = ((sides - 1) // 2)[bucket]
    u0, v0 = torch.floor(u.detach()), torch.floor(v.detach())
    keep = on_level[bucket] & (inst["z"].detach() > NEAR) & (u0 + half + 1 >= 0) \
        & (u0 - half <= width - 1) & (v0 + half + 1 >= 0) & (v0 - half <= height - 1)
    sel = torch.nonzero(keep).squeeze(1)
    order = torch.sort(bucket[sel], stable=True)
    sel = sel[order.indices]
    counts = torch.bincount(order.values, minlength=len(stamps.buckets)).tolist()
    plan, start = [], 0
    for b, count in enumerate(counts):
        if count == 0:
            continue
        bk = stamps.buckets[b]
        per_chunk = max(1, chunk_elements // ((bk.side + 1) ** 2))
        end = start + count
        plan.extend((bk, sel[s0:min(s0 + per_chunk, end)])
                    for s0 in range(start, end, per_chunk))
        start = end
    return plan


class _Chunk:
    """One chunk of instances that share a stamp side: their patches on the pixel grid.

    Shape: slots, u, v, target (n,); ``pix`` (n, s+1, s+1) flat indices into the (2 B H W,)
    accumulators (clamped to the image), ``valid`` the same shape, true inside the image;
    ``fu``, ``fv`` (n, 1, 1) sub-pixel fractions; ``s11 s10 s01 s00`` (n, s+1, s+1) the stamp
    shifted by (0, 0), (0, 1), (1, 0), (1, 1) pixels (rows, columns).
    """

    def __init__(self, bk: StampBucket, slots, u, v, target, height, width):
        side = bk.side
        half = (side - 1) // 2
        u0, v0 = torch.floor(u), torch.floor(v)
        ramp = torch.arange(side + 1, device=u.device)
        stamp = F.pad(bk.stamps[slots], (1, 1, 1, 1))                   # (n, s+2, s+2)
        self.fu = (u - u0)[:, None, None]
        self.fv = (v - v0)[:, None, None]
        self.s11, self.s10 = stamp[:, 1:, 1:], stamp[:, 1:, :-1]
        self.s01, self.s00 = stamp[:, :-1, 1:], stamp[:, :-1, :-1]
        xs = u0.long()[:, None] - half + ramp                           # (n, s+1)
        ys = v0.long()[:, None] - half + ramp
        self.valid = ((ys >= 0) & (ys < height))[:, :, None] & ((xs >= 0) & (xs < width))[:, None, :]
        self.pix = (target[:, None, None] * height + ys.clamp(0, height - 1)[:, :, None]) * width \
            + xs.clamp(0, width - 1)[:, None, :]

    def rows(self):
        """The stamp shifted by the sub-pixel column fraction, at the patch's two row shifts:
        ``(top, bottom)``, each (n, s+1, s+1); the patch is ``lerp(top, bottom, fv)``."""
        return torch.lerp(self.s11, self.s10, self.fu), torch.lerp(self.s01, self.s00, self.fu)

    def patch(self):
        """Bilinear splat: patch[i, j] mixes stamp[i - a, j - b] for a, b in {0, 1}."""
        top, bottom = self.rows()
        return torch.lerp(top, bottom, self.fv)

    def visibility(self, scaled_depth, z, beta):
        """V = 1 / (1 + exp(β (d − D))) under every patch pixel, from ``scaled_depth`` = β D.
        Shape: (n, s+1, s+1)."""
        # index_select: several times faster than advanced indexing for a 1-D gather on the CPU
        under = scaled_depth.index_select(0, self.pix.reshape(-1)).view(self.pix.shape)
        return torch.sigmoid(under - (beta * z)[:, None, None])


class _Splat(torch.autograd.Function):
    """Scatter-add every instance's weighted stamp into ``A = Σ θ B V`` and ``C_c = Σ γ_c θ B V``.

    The forward pass keeps nothing per patch pixel and the backward pass recomputes each chunk and
    applies the chain rule by hand, so memory with gradients is bounded by the chunk size too, not
    by the total footprint of all particles (which autograd would otherwise keep: patches,
    visibilities and pixel indices of every chunk).
    Shape: u, v, z, theta (I,), color (I, 3) -> (4, 2 B H W): A, C_r, C_g, C_b.
    """

    @staticmethod
    def forward(ctx, u, v, z, theta, color, target, slots, depth_flat, plan, height, width,
                beta):
        size = depth_flat.numel()
        acc = torch.zeros(4, size, dtype=u.dtype, device=u.device)
        scaled = beta * depth_flat
        for bk, idx in plan:
            c = _Chunk(bk, slots[idx], u[idx], v[idx], target[idx], height, width)
            weight = c.patch().mul_(c.visibility(scaled, z[idx], beta))
            weight = weight.mul_(theta[idx][:, None, None]).mul_(c.valid).reshape(-1)
            flat = c.pix.reshape(-1)
            # Four 1-D scatters: much faster than one scatter of (M, 4) rows on the CPU.
            acc[0].index_add_(0, flat, weight)
            col = color[idx]
            per_instance = weight.view(idx.numel(), -1)
            for ch in range(3):
                acc[ch + 1].index_add_(0, flat, (per_instance * col[:, ch, None]).reshape(-1))
        ctx.save_for_backward(u, v, z, theta, color, target, slots, depth_flat)
        ctx.plan, ctx.height, ctx.width, ctx.beta = plan, height, width, beta
        return acc

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_acc):
        u, v, z, theta, color, target, slots, depth_flat = ctx.saved_tensors
        need = ctx.needs_input_grad[:5]
        grads = [torch.zeros_like(t) if n else None for t, n in zip((u, v, z, theta, color), need)]
        beta = ctx.beta
        scaled = beta * depth_flat
        g_rows = g_acc.t().contiguous() if any(need) else None          # (size, 4): one gather
        for bk, idx in ctx.plan if any(need) else ():
            c = _Chunk(bk, slots[idx], u[idx], v[idx], target[idx], ctx.height, ctx.width)
            n, p = idx.numel(), (bk.side + 1) ** 2
            th = theta[idx][:, None, None]
            vis = c.visibility(scaled, z[idx], beta).mul_(c.valid)
            top, bottom = c.rows()
            patch = torch.lerp(top, bottom, c.fv)
            g_here = g_rows.index_select(0, c.pix.reshape(-1)).view(n, p, 4)  # dL/d(A, C_rgb)
            # dL/dweight of every patch pixel: the opacity sum and the colour sums
            ones_col = torch.cat((torch.ones_like(theta[idx])[:, None], color[idx]), 1)
            g_weight = torch.bmm(g_here, ones_col[:, :, None]).view_as(patch)
            g_bv = g_weight * vis                                        # dL/d(θ B) per pixel
            if need[0]:
                d_fu = torch.lerp(c.s10 - c.s11, c.s00 - c.s01, c.fv)
                grads[0].index_add_(0, idx, th[:, 0, 0] * (g_bv * d_fu).sum((1, 2)))
            if need[1]:
                grads[1].index_add_(0, idx, th[:, 0, 0] * (g_bv * (bottom - top)).sum((1, 2)))
            g_bvp = g_bv * patch if need[2] or need[3] else None         # dL/dθ per pixel
            if need[2]:  # dV/dd = −β V (1 − V): dL/dd = −β θ Σ g B V (1 − V)
                grads[2].index_add_(0, idx, (-beta) * th[:, 0, 0]
                                    * (g_bvp - g_bvp * vis).sum((1, 2)))
            if need[3]:
                grads[3].index_add_(0, idx, g_bvp.sum((1, 2)))
            if need[4]:
                weight = (patch * vis * th).view(n, 1, p)
                grads[4].index_add_(0, idx, torch.bmm(weight, g_here)[:, 0, 1:])
        return (*grads, None, None, None, None, None, None, None)


def _splat(depths, inst, stamps: StampSet, height, width, beta, chunk_elements,
           detach_occlusion: bool = False):
    """The per-pixel sums A, C_r, C_g, C_b, shape (4, V H W), of every instance's weighted
    stamp, or None when no instance reaches the image; see :class:`_Splat`. Also returns which
    pairs of the batch, (B,) bool, an instance reaches (B = V / 2; a single view counts as one
    pair).

    ``depths``: the scene depth of the V views, (2, B, 1, H, W) for a batch of pairs or any
    shape of V H W elements (one view: (1, H, W)). Coarse buckets (large billboards) are
    splatted on their own grid, ``f`` times coarser: positions ``(u + 0.5) / f − 0.5``, scene depth averaged over
    f x f blocks; coarser grids are upsampled bilinearly into finer ones, coarsest first, and
    the result into the image grid. ``detach_occlusion``: the particle depth reaches ``V`` without
    gradient (positions still get theirs through the bilinear splat).
    """
    depths = depths.reshape(-1, 1, height, width)
    z = inst["z"].detach() if detach_occlusion else inst["z"]
    bsz = max(1, depths.shape[0] // 2)
    reached = torch.zeros(bsz, dtype=torch.bool, device=depths.device)
    slots = stamps.slot_of[inst["particle"]]
    carry = None        # the coarser levels' sums, (4 * 2B, 1, h, w)
    levels = sorted({bk.coarse for bk in stamps.buckets}, reverse=True)
    pooled = _depth_levels(depths.detach(), [c for c in levels if c > 0])
    for i, coarse in enumerate(levels):
        f = 2 ** coarse
        if coarse == 0:
            h, w, u, v, depth = height, width, inst["u"], inst["v"], depths
        else:
            h, w = -(-height // f), -(-width // f)
            u, v = (inst["u"] + 0.5) / f - 0.5, (inst["v"] + 0.5) / f - 0.5
            depth = pooled[coarse]
        plan = _splat_plan(inst, stamps, h, w, chunk_elements, coarse, u, v)
        for _, sel in plan:
            reached[inst["target"][sel] % bsz] = True
        sums = None
        if plan:
            sums = _Splat.apply(u, v, z, inst["theta"], inst["color"], inst["target"],
                                slots, depth.detach().reshape(-1), plan, h, w,
                                beta).view(-1, 1, h, w)
        if carry is not None:  # bring the coarser levels to this grid, one upsampling each
            up = upsample(carry, 2 ** (levels[i - 1] - coarse), (h, w))
            sums = up if sums is None else sums + up
        carry = sums
    if carry is not None and levels[-1] > 0:
        carry = upsample(carry, 2 ** levels[-1], (height, width))
    return (None if carry is None else carry.reshape(4, -1)), reached


def _depth_levels(depths: torch.Tensor, levels: Sequence[int]) -> dict:
    """The scene depth averaged over f x f blocks (f = 2**level; the image edge replicated up to
    a whole block) for each coarse level. Shape: (V, 1, H, W) -> {level: (V, 1, h, w)}."""
    height, width = depths.shape[-2:]
    out = {}
    for level in levels:
        f = 2 ** level
        pad = (0, -width % f, 0, -height % f)
        out[level] = F.avg_pool2d(F.pad(depths, pad, mode="replicate") if any(pad) else depths, f)
    return out


def check_records(records: Sequence[Particles],
                  templates: Optional[TemplateLibrary] = None) -> TemplateLibrary:
    """The template library the records of one render call are drawn with (``templates``, or
    the one their settings name), after checking that they share it, that it is the library
    they were sampled with, and their blend modes. Raises ConfigError."""
    if templates is None:
        names = {r.settings.templates for r in records}
        if len(names) != 1:
            raise ConfigError(f"records of one render call must share templates; got {sorted(names)}")
        templates = load_templates(names.pop())
    for r in records:
        if r.settings.templates_digest and templates.digest != r.settings.templates_digest:
            raise ConfigError(f"particles were sampled with templates '{r.settings.templates}' "
                              f"(digest {r.settings.templates_digest}) but are rendered with "
                              f"'{templates.name}' (digest {templates.digest})")
        if r.settings.blend not in BLEND_MODES:
            raise ConfigError(f"unknown blend mode {r.settings.blend!r}")
    return templates


def render(image1: torch.Tensor, image2: torch.Tensor, depth1: torch.Tensor,
           depth2: torch.Tensor, intrinsics: torch.Tensor, cam1_from_ref: torch.Tensor,
           cam2_from_ref: torch.Tensor, particles: Union[Particles, Sequence[Particles]],
           templates: Optional[TemplateLibrary] = None, *, beta: float = BETA_RENDER,
           stamps: Optional[StampSet] = None,
           chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
           coarse_side: Optional[int] = COARSE_SIDE,
           detach_occlusion: bool = False) -> RenderOutput:
    """Render particle records into a batch of frame pairs.

    Shape:
        image1, image2: (B, 3, H, W) float in [0, 1]; depth1, depth2: (B, 1, H, W) camera-z.
        intrinsics: (B, 3, 3); cam1_from_ref, cam2_from_ref: (B, 4, 4), the cameras' transforms
            from each record's reference frame (see :func:`reference_transforms`).
        particles: one record per pair (a single record for B = 1).
    Computes in the images' dtype and device. Returns :class:`RenderOutput`.
    ``coarse_side``: stamps at least this wide are splatted on a coarser grid and upsampled
    (see :func:`build_stamps`); ``None`` renders every stamp at full resolution. Ignored when
    ``stamps`` are given (they carry their own grids) and for weather-field records (their
    per-frame path uses the default). ``detach_occlusion``: the visibility ``V`` passes no
    gradient to the particles' depth (the same forward pass).
    """
    records = [particles] if isinstance(particles, Particles) else list(particles)
    if image1.dim() != 4 or image1.shape[1] != 3 or image2.shape != image1.shape:
        raise ShapeError(f"images must be (B, 3, H, W) and equal; got {tuple(image1.shape)} "
                         f"and {tuple(image2.shape)}")
    bsz, _, height, width = image1.shape
    for name, d in (("depth1", depth1), ("depth2", depth2)):
        if d is None:
            raise DatasetError(f"{name} is missing; weather rendering needs scene depth")
        if tuple(d.shape) != (bsz, 1, height, width):
            raise ShapeError(f"{name} has shape {tuple(d.shape)}, expected "
                             f"{(bsz, 1, height, width)}")
    if len(records) != bsz:
        raise ConfigError(f"{len(records)} particle records for a batch of {bsz} frame pairs")
    dtype, device = image1.dtype, image1.device
    templates = check_records(records, templates)

    if any(r.optics is not None for r in records):
        # Weather-field records look different in each frame: one view at a time (perframe.py).
        return PER_FRAME_RENDERER(image1, image2, depth1, depth2, intrinsics.to(device),
                                cam1_from_ref.to(device), cam2_from_ref.to(device), records,
                                templates, beta=beta, chunk_elements=chunk_elements,
                                detach_occlusion=detach_occlusion)

    acc = None
    reached = torch.zeros(bsz, dtype=torch.bool, device=device)
    intr = intrinsics.to(device)
    inst = _instances(records, intr, cam1_from_ref.to(device), cam2_from_ref.to(device),
                      dtype, device)
    if inst is not None:
        if stamps is None:
            stamps = build_stamps(records, templates, dtype=dtype, device=device,
                                  chunk_elements=chunk_elements, coarse_side=coarse_side)
        depths = torch.stack((depth1, depth2)).to(dtype)
        acc, reached = _splat(depths, inst, stamps, height, width, float(beta), chunk_elements,
                              detach_occlusion)
    return blend_sums(acc, image1, image2, records, reached)


def blend_sums(acc: Optional[torch.Tensor], image1: torch.Tensor, image2: torch.Tensor,
           records: Sequence[Particles], reached: torch.Tensor) -> RenderOutput:
    """Blend the per-pixel sums ``acc`` (4, 2 B H W) of A, C_r, C_g, C_b (None: nothing was
    splatted) into both frames, each pair with its record's blend mode. Shape: images
    (B, 3, H, W); returns :class:`RenderOutput`."""
    bsz, _, height, width = image1.shape
    if acc is None:
        acc = torch.zeros(4, 2 * bsz * height * width, dtype=image1.dtype, device=image1.device)
    # blending both frames is one autograd node with a hand-written backward (compositing.py)
    alpha_mode = torch.tensor([r.settings.blend == "alpha" for r in records],
                              device=image1.device)
    out1, out2, opacity1, opacity2 = blend(acc.view(4, 2, bsz, 1, height, width), image1,
                                           image2, alpha_mode)
    return RenderOutput(image1=out1, image2=out2, opacity1=opacity1, opacity2=opacity2,
                        reached=reached)


def render_pair(pair: Union[FramePair, FramePairBatch],
                particles: Union[Particles, Sequence[Particles]],
                templates: Optional[TemplateLibrary] = None, *, beta: float = BETA_RENDER,
                device=None, stamps: Optional[StampSet] = None,
                coarse_side: Optional[int] = COARSE_SIDE,
                detach_occlusion: bool = False) -> RenderOutput:
    """Render particles into a :class:`FramePair` (B = 1) or a :class:`FramePairBatch`.

    Picks each record's reference transforms from the pair's poses; raises ConfigError when a
    record sampled in world coordinates meets a pair without absolute poses.
    ``detach_occlusion`` as for :func:`render`.
    Shape: returns images (B, 3, H, W) and opacities (B, 1, H, W).
    """
    dev = resolve_device(device) if device is not None else None
    if isinstance(pair, FramePair):
        check_pair_for_engine(pair)
        if dev is not None:
            pair = pair.to(dev)
        frame, c1, c2 = reference_transforms(pair)
        records = [particles] if isinstance(particles, Particles) else list(particles)
        fields = dict(image1=pair.image1[None], image2=pair.image2[None],
                      depth1=pair.depth1[None], depth2=pair.depth2[None],
                      intrinsics=pair.intrinsics[None])
        frames, c1, c2 = [frame], c1[None], c2[None]
    else:
        if pair.depth1 is None or pair.depth2 is None:
            raise DatasetError("frame-pair batch has no depth; weather rendering needs depth")
        world = pair.cam1_from_world is not None and pair.cam2_from_world is not None
        bsz = pair.image1.shape[0]
        if world:
            c1, c2, frames = pair.cam1_from_world, pair.cam2_from_world, ["world"] * bsz
        else:
            c1 = torch.eye(4, dtype=torch.float64).expand(bsz, 4, 4)
            c2, frames = pair.cam2_from_cam1, ["camera1"] * bsz
        records = list(particles) if not isinstance(particles, Particles) else [particles]
        fields = dict(image1=pair.image1, image2=pair.image2, depth1=pair.depth1,
                      depth2=pair.depth2, intrinsics=pair.intrinsics)
        if dev is not None:
            fields = {k: v.to(dev) for k, v in fields.items()}
    for rec, frame in zip(records, frames):
        if rec.frame != frame:
            raise ConfigError(f"particles live in {rec.frame} coordinates but the frame pair "
                              f"offers {frame} coordinates (sample them for this pair)")
    if dev is not None:
        records = [r.to(dev) for r in records]
    return render(**fields, cam1_from_ref=c1, cam2_from_ref=c2, particles=records,
                  templates=templates, beta=beta, stamps=stamps, coarse_side=coarse_side,
                  detach_occlusion=detach_occlusion)
