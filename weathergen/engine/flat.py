"""The renderer's forward pass in a fixed number of tensor operations, for training batches.

:func:`~weathergen.engine.render` groups particles into buckets of equal stamp side and pays a
fixed set of tensor operations per bucket (rasterising, blurring, planning and splatting), a few
dozen buckets per batch and a few hundred operations per disc blur. On a GPU every operation is a
kernel launch with Python around it, and their number, not their arithmetic, sets the time of a
training batch's weather. :func:`render_flat` computes the same frames with the particles laid
out *ragged*: every particle's stamp pixels, every output pixel's blur rows and every blur
sample's patch pixels are one flat run of a long tensor, located by ``repeat_interleave`` and
offsets, so a whole batch costs a few hundred operations whatever the particles' sizes (plus a
handful per chunk of :data:`FLAT_CHUNK_ELEMENTS` elements, which bounds the memory).

The model is the renderer's, step for step (see :mod:`weathergen.engine.renderer`): the same stamp
sides, supersampling, mip levels, disc test, disc blur and brightening, coarse grids for large
billboards, blur samples, visibility and blending. What differs is arithmetic order:

- the template is sampled by hand-written bilinear interpolation (``grid_sample``'s formula, zero
  padding by a one-pixel border) from a flat atlas of every mip level;
- the disc blur sums each disc row from row prefix sums (``cumsum``) in float64, instead of
  adding shifted copies (or an FFT for large stamps); where a row is all zeros the difference of
  prefix sums is exactly zero, so blurred stamps stay exactly zero outside their support;
- stamps are computed in ``stamp_dtype`` (float64 by default) and splatted in the images' dtype.

So the frames equal :func:`~weathergen.engine.render`'s up to float rounding (tested against it
in float64 to 1e-9 and in float32 to 1e-3, a quarter of a grey level). There is no backward
pass: this is for augmentation, where nothing is differentiated; attacks use
:func:`~weathergen.engine.render`.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from ..errors import ConfigError
from .compositing import upsample
from .particles import Particles
from .renderer import (BETA_RENDER, COARSE_MAX_LEVEL, COARSE_SIDE, RIM_MARGIN, RenderOutput,
                       _blur_steps, _depth_levels, blend_sums, check_records, defocus_brighten,
                       mip_pyramid, stamp_geometry)
from .sampling import NEAR
from .templates import TemplateLibrary

#: Ragged elements (stamp samples, blur rows, patch pixels) handled per chunk on the CPU; each
#: costs up to about :data:`BYTES_PER_ELEMENT` bytes of temporaries (a few hundred MiB here).
FLAT_CHUNK_ELEMENTS = 1 << 21
#: Temporaries per ragged element, bytes (an upper estimate, for sizing chunks on a GPU).
BYTES_PER_ELEMENT = 256
#: On a GPU, chunks take at most this share of the free memory (and at most 2**25 elements):
#: fewer chunks, fewer kernel launches.
GPU_MEMORY_SHARE = 0.25


def chunk_elements_for(device: torch.device) -> int:
    """The default chunk size on ``device``: :data:`FLAT_CHUNK_ELEMENTS` on the CPU; on a CUDA
    device as many elements as :data:`GPU_MEMORY_SHARE` of its free memory holds, between
    2**21 and 2**25."""
    if device.type != "cuda":
        return FLAT_CHUNK_ELEMENTS
    free, _ = torch.cuda.mem_get_info(device)
    return int(min(1 << 25, max(1 << 21, GPU_MEMORY_SHARE * free // BYTES_PER_ELEMENT)))


_ATLAS_CACHE: dict = {}
_FLOAT_FIELDS = ("position", "motion", "offset1", "offset2", "color")


def _atlas(lib: TemplateLibrary, dtype, device) -> tuple:
    """Every mip level of every template with a one-pixel zero border, flattened into one tensor.

    Returns ``(atlas, first (L,) int64 offset of each level, sides (L,) int64 R_L)``; template
    ``t``'s pixel ``(y, x)`` of level ``L`` sits at ``first[L] + (t (R_L + 2) + y + 1) (R_L + 2)
    + x + 1``. The atlas ends in a row of zeros, so that a bilinear read ``at``, ``at + 1``,
    ``at + R_L + 2``, ``at + R_L + 3`` stays inside it for any ``at`` up to its last pixel.
    """
    key = (lib.digest, lib.name, dtype, str(device))
    if key not in _ATLAS_CACHE:
        levels = mip_pyramid(lib, dtype, device)
        padded = [torch.nn.functional.pad(lv[:, 0], (1, 1, 1, 1)).reshape(-1) for lv in levels]
        sizes = [p.numel() for p in padded]
        first = torch.tensor([sum(sizes[:i]) for i in range(len(sizes))], device=device)
        sides = torch.tensor([lv.shape[-1] for lv in levels], device=device)
        if len(_ATLAS_CACHE) > 16:
            _ATLAS_CACHE.clear()
        tail = torch.zeros(lib.resolution + 4, dtype=dtype, device=device)
        _ATLAS_CACHE[key] = (torch.cat(padded + [tail]), first, sides)
    return _ATLAS_CACHE[key]


def _runs(sizes: torch.Tensor, limit: int):
    """Split items with ``sizes`` elements each (a ragged layout) into chunks of about ``limit``
    elements (an item larger than that is a chunk of its own). Yields, per chunk,
    ``(item (m,), local (m,))``: each element's item index and its index inside the item's run.
    Two host synchronisations for the whole layout (plus one per extra chunk)."""
    count = int(sizes.numel())
    if count == 0:
        return
    ends = torch.cumsum(sizes, 0)
    total = int(ends[-1])
    if total == 0:
        return
    if total <= limit:
        cuts = [0, count]
        bounds = [0, total]
    else:
        marks = torch.arange(limit, total, limit, device=sizes.device)
        inner = torch.unique(torch.searchsorted(ends, marks, right=True).clamp(1, count - 1))
        cut_t = torch.cat((inner.new_zeros(1), inner, inner.new_full((1,), count)))
        cuts = cut_t.tolist()
        bounds = [0] + ends[cut_t[1:] - 1].tolist()
    starts = ends - sizes
    for a, b, lo, hi in zip(cuts[:-1], cuts[1:], bounds[:-1], bounds[1:]):
        if hi == lo:
            continue
        items = torch.arange(a, b, device=sizes.device)
        item = torch.repeat_interleave(items, sizes[a:b], output_size=hi - lo)
        local = torch.arange(lo, hi, device=sizes.device) - starts[item]
        yield item, local


def _disc_counts(radius: torch.Tensor) -> torch.Tensor:
    """Taps of the disc of each radius r (integer offsets with dx² + dy² <= r²). Shape: (n,)."""
    top = int(radius.max()) if radius.numel() else 0
    dy = torch.arange(-top, top + 1, device=radius.device, dtype=torch.float64)
    r2 = (radius.to(torch.float64) ** 2)[:, None]
    rows = torch.floor(torch.sqrt((r2 - dy * dy).clamp(min=0)))
    inside = dy.abs() <= radius.to(torch.float64)[:, None]
    return ((2 * rows + 1) * inside).sum(1)


class _Layout:
    """The particles of a render call, concatenated in record order (the renderer's global
    particle index), with their stamp geometry; all tensors (P,)."""

    def __init__(self, records: Sequence[Particles], lib: TemplateLibrary, device, dtype,
                 stamp_dtype, coarse_side):
        counts = [r.count for r in records]
        self.count = sum(counts)

        host = records[0].position.device

        def joined(name):
            return torch.cat([getattr(r, name).to(host) for r in records])

        # two copies to the device: the reals, in float64, and the integers
        reals = torch.cat([joined(f).to(torch.float64).view(self.count, 3 if i < 5 else 1)
                           for i, f in enumerate(_FLOAT_FIELDS + ("transparency", "rotation",
                                                                   "scale"))], 1)
        flags = torch.tensor([[i, int(bool(r.settings.defocus_brighten))]
                              for i, r in enumerate(records)], device=host)
        flags = torch.repeat_interleave(flags, torch.tensor(counts, device=host), dim=0,
                                        output_size=self.count)
        ints = torch.cat((torch.stack((joined("template").long(), joined("defocus").long()), 1),
                          flags), 1)
        reals, ints = reals.to(device), ints.to(device)
        # positions stay in float64 (blur samples are projected in float64)
        self.position, self.motion, self.offset1, self.offset2 = (
            reals[:, 3 * i:3 * i + 3] for i in range(4))
        self.color = reals[:, 12:15].to(dtype)
        self.transparency = reals[:, 15].to(dtype)
        self.template, defocus, self.record, bright = ints.unbind(1)
        if self.count and (int(self.template.min()) < 0 or int(self.template.max()) >= lib.count):
            raise ConfigError(f"particle template index out of range for the {lib.count} "
                              f"templates of '{lib.name}'")
        rotation = reals[:, 16].to(stamp_dtype)
        footprint = (reals[:, 17] * lib.resolution).clamp(min=1.0)
        self.brighten = (bright > 0) & (defocus > 1)
        _, _, level_sides = _atlas(lib, stamp_dtype, device)
        footprint, radius, coarse, self.side, self.sub, self.level = stamp_geometry(
            footprint, defocus, lib.resolution, level_sides.numel(), coarse_side)
        self.radius, self.coarse = radius, coarse
        self.full_side = self.side + 2 * radius          # the stamp's side after its blur
        self.cos, self.sin = torch.cos(rotation), torch.sin(rotation)
        self.half = footprint.to(stamp_dtype) / 2


def _rasterise(lay: _Layout, lib: TemplateLibrary, stamp_dtype, chunk: int) -> tuple:
    """Every particle's stamp before its blur, ragged: ``(pixels (sum of side²,), first (P,))``.

    Each pixel averages ``sub x sub`` bilinear samples of the template's mip level at the rotated
    and scaled sample position, zero outside the footprint's disc (:func:`renderer._stamp_chunk`).
    """
    atlas, level_first, level_sides = _atlas(lib, stamp_dtype, lay.position.device)
    last = atlas.numel() - lib.resolution - 5               # the last pixel before the zero tail
    side, sub = lay.side, lay.sub
    npix = side * side
    first = torch.cumsum(npix, 0) - npix
    pixels = torch.zeros(int(npix.sum()), dtype=stamp_dtype, device=atlas.device)
    across = side * sub                                           # samples along a row
    res = level_sides[lay.level]
    # A sample ``k`` along a row sits at ``g = (k + 0.5) / sub − 0.5 − h`` pixels from the centre;
    # its place in the template level (grid_sample's pixel coordinates, align_corners=False) is
    # ``centre + R (g cos + g' sin) / (2 half)``: per particle the scale ``a``, ``b`` of the
    # rotation, the centre and the disc's squared radius in those units.
    r = res.to(stamp_dtype)
    scale = r / (2 * lay.half)
    ints = torch.stack((across, sub, side, first, res + 2,
                        level_first[lay.level] + lay.template * (res + 2) ** 2), 1)
    reals = torch.stack((lay.cos * scale, lay.sin * scale, (r - 1) / 2,
                         (r / 2) ** 2 * (1.0 + RIM_MARGIN), 1.0 / sub.to(stamp_dtype),
                         0.5 / sub.to(stamp_dtype) - 0.5 - ((side - 1) // 2).to(stamp_dtype)), 1)
    for p, local in _runs(across * across, chunk):
        n, s_p, sd, fst, stride, base = ints[p].unbind(1)
        a, b, centre, radius2, step, offset = reals[p].unbind(1)
        row = torch.div(local, n, rounding_mode="floor")
        col = local - row * n
        gx, gy = col * step + offset, row * step + offset
        dx, dy = a * gx + b * gy, a * gy - b * gx
        inside = dx * dx + dy * dy <= radius2
        ix, iy = dx + centre, dy + centre
        x0, y0 = torch.floor(ix), torch.floor(iy)
        # samples outside the disc may point anywhere: clamped into the atlas, then zeroed
        at = (base + (y0 + 1) * stride + x0 + 1).clamp(0, last).long()
        value = torch.lerp(torch.lerp(atlas[at], atlas[at + 1], ix - x0),
                           torch.lerp(atlas[at + stride], atlas[at + stride + 1], ix - x0), iy - y0)
        target = fst + torch.div(row, s_p, rounding_mode="floor") * sd \
            + torch.div(col, s_p, rounding_mode="floor")
        pixels.index_add_(0, target, value * inside)
    pixels = pixels / torch.repeat_interleave((sub * sub).to(stamp_dtype), npix,
                                              output_size=pixels.numel())
    return pixels, first


def _blur(lay: _Layout, pixels: torch.Tensor, first: torch.Tensor, chunk: int) -> tuple:
    """Every particle's final stamp (disc-blurred where its radius is > 0, brightened where
    flagged), ragged with a one-pixel zero border: ``(stamps, first (P,))``, particle ``p``'s
    pixel ``(y, x)`` at ``first[p] + (y + 1) (S + 2) + x + 1`` with ``S = side + 2 radius``.

    A blurred pixel sums, over the disc's rows ``dy``, the stamp's row ``y − r + dy`` between
    columns ``x − r ∓ w(dy)``, read as a difference of the row's prefix sums; a stamp without
    blur (one row, ``r = 0``) is copied.
    """
    side, radius, full = lay.side, lay.radius, lay.full_side
    block = (full + 2) * (full + 2)
    out_first = torch.cumsum(block, 0) - block
    out = torch.zeros(int(block.sum()), dtype=pixels.dtype, device=pixels.device)
    prefix = torch.cat((pixels.new_zeros(1), torch.cumsum(pixels.to(torch.float64), 0)))
    rows = 2 * radius + 1
    ints = torch.stack((rows, radius, side, full, first, out_first), 1)
    for p, local in _runs(full * full * rows, chunk):
        n, r, s, S, fst, ofst = ints[p].unbind(1)
        pix = torch.div(local, n, rounding_mode="floor")
        dy = local - pix * n - r
        y_out = torch.div(pix, S, rounding_mode="floor")
        x_out = pix - y_out * S
        w = torch.floor(torch.sqrt((r * r - dy * dy).to(torch.float64))).long()
        y = y_out - r + dy
        a = (x_out - r - w).clamp(min=0)
        b = (x_out - r + w).minimum(s - 1)
        start = fst + y.clamp(min=0) * s
        at_a = (start + a).clamp(max=pixels.numel() - 1)
        at_b = (start + b + 1).clamp(max=pixels.numel())
        value = torch.where(r == 0, pixels[at_a].to(prefix.dtype), prefix[at_b] - prefix[at_a])
        value = torch.where((y >= 0) & (y < s) & (a <= b), value, prefix.new_zeros(()))
        out.index_add_(0, ofst + (y_out + 1) * (S + 2) + x_out + 1, value.to(out.dtype))
    sharp = radius == 0
    weight = torch.where(sharp, 1.0, 1.0 / _disc_counts(radius)).to(out.dtype)
    brighten = torch.stack((weight, lay.brighten.to(out.dtype)), 1)
    weight, brighten = torch.repeat_interleave(brighten, block, dim=0,
                                               output_size=out.numel()).unbind(1)
    out = out * weight
    out = torch.where(brighten > 0, defocus_brighten(out), out)
    return out, out_first


def _instances(lay: _Layout, records, intrinsics, cam1_from_ref, cam2_from_ref, dtype) -> dict:
    """Every particle's blur samples in both frames, projected: flat tensors (I,) of ``u``,
    ``v``, ``z``, ``theta`` (θ / K), ``target`` (frame t * B + pair), ``particle``, and ``color``
    (I, 3); one pass per distinct (blur samples, blur length) among the records."""
    device = lay.position.device
    bsz = len(records)
    groups: dict = {}
    for i, r in enumerate(records):
        steps = _blur_steps(r, dtype, torch.device("cpu"))
        groups.setdefault(tuple(steps.tolist()), []).append(i)
    k_all = intrinsics.to(device, torch.float64)
    proj1, proj2 = (k_all @ c.to(device, torch.float64)[:, :3, :]
                    for c in (cam1_from_ref, cam2_from_ref))
    parts = []
    for steps, members in groups.items():
        if len(groups) == 1:
            index = None
        else:
            chosen = torch.zeros(bsz, dtype=torch.bool, device=device)
            chosen[members] = True
            index = torch.nonzero(chosen[lay.record]).squeeze(1)
        pick = (lambda t: t) if index is None else (lambda t: t[index])  # noqa: E731
        rec = pick(lay.record)
        start = pick(lay.position) + pick(lay.offset1)
        end = start + pick(lay.motion) + pick(lay.offset2)
        # K (R X + t) per frame: the blur samples X_t + s (X2 − X1) of camera space are
        # K X_t + s (K X2 − K X1) in homogeneous image coordinates (z the camera depth)
        h1 = (proj1[rec] @ torch.cat((start, torch.ones_like(start[:, :1])), 1)[:, :, None])
        h2 = (proj2[rec] @ torch.cat((end, torch.ones_like(end[:, :1])), 1)[:, :, None])
        h1, h2 = h1[:, :, 0], h2[:, :, 0]
        k = len(steps)
        step = torch.tensor(steps, dtype=torch.float64, device=device)
        pts = torch.stack((h1, h2))[:, :, None, :] + step[:, None] * (h2 - h1)[None, :, None, :]
        z = pts[..., 2]
        safe = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
        u, v = (pts[..., :2] / safe[..., None]).to(dtype).unbind(-1)
        z = z.to(dtype)
        n = rec.numel()
        particle = torch.arange(lay.count, device=device) if index is None else index
        frame = torch.arange(2, device=device)[:, None, None]
        parts.append(dict(
            u=u.reshape(-1), v=v.reshape(-1), z=z.reshape(-1),
            theta=(pick(lay.transparency) / k)[None, :, None].expand(2, n, k).reshape(-1),
            target=(frame * bsz + rec[None, :, None]).expand(2, n, k).reshape(-1),
            particle=particle[None, :, None].expand(2, n, k).reshape(-1),
            color=pick(lay.color)[None, :, None, :].expand(2, n, k, 3).reshape(-1, 3)))
    if len(parts) == 1:
        return parts[0]
    return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}


def render_flat(image1: torch.Tensor, image2: torch.Tensor, depth1: torch.Tensor,
                depth2: torch.Tensor, intrinsics: torch.Tensor, cam1_from_ref: torch.Tensor,
                cam2_from_ref: torch.Tensor, records: Sequence[Particles],
                templates: Optional[TemplateLibrary] = None, *, beta: float = BETA_RENDER,
                chunk_elements: Optional[int] = None,
                coarse_side: Optional[int] = COARSE_SIDE,
                stamp_dtype: torch.dtype = torch.float64) -> RenderOutput:
    """Render one paper-model record per pair, as :func:`~weathergen.engine.render` does (same
    arguments; the shapes and reference frames are the caller's to check, see
    :func:`weathergen.training.batchrender.render_records`), in a fixed number of tensor
    operations and without gradients (see the module doc). ``templates``: default, the library
    the records name. ``chunk_elements``: default :func:`chunk_elements_for` the device.

    Shape: images (B, 3, H, W), depths (B, 1, H, W), intrinsics (B, 3, 3), transforms
    (B, 4, 4); returns :class:`RenderOutput` with images (B, 3, H, W), opacities (B, 1, H, W).
    """
    templates = check_records(records, templates)
    if any(r.optics is not None for r in records):
        raise ConfigError("render_flat renders the paper's particle records; weather-field "
                          "records are rendered view by view (weathergen.engine.render)")
    bsz, _, height, width = image1.shape
    dtype, device = image1.dtype, image1.device
    if chunk_elements is None:
        chunk_elements = chunk_elements_for(device)
    with torch.no_grad():
        lay = _Layout(records, templates, device, dtype, stamp_dtype, coarse_side)
        reached = torch.zeros(bsz, dtype=torch.bool, device=device)
        acc = None
        if lay.count:
            pixels, first = _rasterise(lay, templates, stamp_dtype, chunk_elements)
            stamps, first = _blur(lay, pixels, first, chunk_elements)
            inst = _instances(lay, records, intrinsics, cam1_from_ref, cam2_from_ref, dtype)
            depths = torch.stack((depth1, depth2)).to(dtype).reshape(-1, 1, height, width)
            acc = _splat(lay, stamps.to(dtype), first, inst, depths, float(beta),
                         chunk_elements, reached)
        return blend_sums(acc, image1, image2, records, reached)


def _splat(lay: _Layout, stamps, first, inst: dict, depths: torch.Tensor, beta: float,
           chunk: int, reached: torch.Tensor) -> Optional[torch.Tensor]:
    """The per-pixel sums A, C_r, C_g, C_b of every blur sample's bilinearly shifted stamp times
    its visibility and θ / K, on every grid at once (full resolution, and the coarse grids of
    large billboards, whose sums are upsampled into the finer ones). Marks ``reached``.
    Shape: depths (2 B, 1, H, W) -> (4, 2 B H W), or None when no sample reaches a frame."""
    views, _, height, width = depths.shape
    device = depths.device
    levels = sorted(set(lay.coarse.unique().tolist()), reverse=True)
    pooled = _depth_levels(depths, [c for c in levels if c > 0])
    grids, offset, flat_depths = {}, 0, []
    for c in levels:
        f = 2 ** c
        h, w = (height, width) if c == 0 else (-(-height // f), -(-width // f))
        grids[c] = (offset, h, w)
        flat_depths.append((depths if c == 0 else pooled[c]).reshape(-1))
        offset += views * h * w
    scaled = beta * torch.cat(flat_depths)
    table = torch.tensor([[*grids.get(c, (0, 1, 1)), 2 ** c] for c in range(COARSE_MAX_LEVEL + 1)],
                         device=device)
    geometry = torch.stack((lay.full_side, lay.coarse), 1)[inst["particle"]]
    side, coarse = geometry.unbind(1)
    start, h, w, f = table[coarse].unbind(1)                    # the particle's grid
    f = f.to(inst["u"].dtype)
    u = torch.where(f > 1, (inst["u"] + 0.5) / f - 0.5, inst["u"])
    v = torch.where(f > 1, (inst["v"] + 0.5) / f - 0.5, inst["v"])
    half = (side - 1) // 2
    u0, v0 = torch.floor(u), torch.floor(v)
    keep = (inst["z"] > NEAR) & (u0 + half + 1 >= 0) & (u0 - half <= w - 1) \
        & (v0 + half + 1 >= 0) & (v0 - half <= h - 1)
    sel = torch.nonzero(keep).squeeze(1)
    if sel.numel() == 0:
        return None
    bsz = views // 2
    target = inst["target"]
    reached[target[sel] % bsz] = True
    # per kept sample, gathered once per chunk: integers (the patch's top-left pixel, its side,
    # the stamp's place, the grid) and reals (sub-pixel shift, β z, θ / K, weights of A and C)
    ints = torch.stack((side + 1, u0.long() - half, v0.long() - half, side + 2,
                        first[inst["particle"]], start + target * h * w, h, w), 1)[sel]
    ones = torch.ones_like(inst["u"])[:, None]
    reals = torch.cat((torch.stack((u - u0, v - v0, beta * inst["z"], inst["theta"]), 1), ones,
                       inst["color"]), 1)[sel]
    acc = torch.zeros(4, offset, dtype=stamps.dtype, device=device)
    for i, local in _runs(ints[:, 0] * ints[:, 0], chunk):
        n, x0, y0, stride, fst, base, hh, ww = ints[i].unbind(1)
        here = reals[i]
        fu, fv, beta_z, theta = here[:, :4].unbind(1)
        row = torch.div(local, n, rounding_mode="floor")
        col = local - row * n
        # the bordered stamp's pixel (row, col) is the stamp's (row − 1, col − 1): the four
        # neighbours stamp[row − a, col − b] (a, b in {0, 1}) are always inside the block
        at = fst + row * stride + col
        top = torch.lerp(stamps[at + stride + 1], stamps[at + stride], fu)
        bottom = torch.lerp(stamps[at + 1], stamps[at], fu)
        value = torch.lerp(top, bottom, fv)
        x, y = x0 + col, y0 + row
        valid = (x >= 0) & (x < ww) & (y >= 0) & (y < hh)
        pix = base + y.clamp(min=0).minimum(hh - 1) * ww + x.clamp(min=0).minimum(ww - 1)
        weight = value * torch.sigmoid(scaled[pix] - beta_z) * theta * valid
        acc.index_add_(1, pix, here[:, 4:].t() * weight)
    out, carry = None, None
    for k, c in enumerate(levels):
        start, h, w = grids[c]
        sums = acc[:, start:start + views * h * w].reshape(-1, 1, h, w)
        if carry is not None:
            sums = sums + upsample(carry, 2 ** (levels[k - 1] - c), (h, w))
        carry = sums
    if levels[-1] > 0:
        carry = upsample(carry, 2 ** levels[-1], (height, width))
    out = carry.reshape(4, -1)
    return out


__all__ = ["FLAT_CHUNK_ELEMENTS", "chunk_elements_for", "render_flat"]
