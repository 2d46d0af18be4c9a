"""The renderer's forward pass in a fixed number of tensor operations, for training batches.

:func:`~weathergen.engine.render` groups particles into buckets of equal stamp side and pays a
fixed set of tensor operations per bucket (rasterising, blurring, planning and splatting), a few
dozen buckets per batch and a few hundred operations per disc blur. On a GPU every operation is a
kernel launch with Python around it, and their number, not their arithmetic, sets the time of a
training batch's weather. :func:`render_flat` computes the same frames with the particles laid
out *ragged*: every particle's stamp samples, the columns each row of its defocus disc reaches
and every blur sample's patch pixels are flat runs of long tensors, located by
``repeat_interleave`` and offsets, so a whole batch costs a few hundred operations whatever the
particles' number and sizes (plus a handful per chunk of :data:`FLAT_CHUNK_ELEMENTS`
elements, which bounds the memory).

The model is the renderer's, step for step (see :mod:`weathergen.engine.renderer`): the same stamp
sides, supersampling, mip levels, disc test, disc blur and brightening, coarse grids for large
billboards, blur samples, visibility and blending; records sampled from a weather field get the
looks :mod:`weathergen.engine.perframe` gives them in each frame (view mask, footprint, depth
fade, thin-lens defocus, softer occlusion), computed for every particle and frame at once. What
differs is arithmetic order:

- the template is sampled by hand-written bilinear interpolation (``grid_sample``'s formula, zero
  padding by a one-pixel border) from a flat atlas of every mip level;
- the disc blur sums each disc row as a difference of the stamp row's prefix sums (``cumsum``)
  in float64, instead of adding shifted copies (or an FFT for large stamps); where a row is all
  zeros the difference is exactly zero, so blurred stamps stay exactly zero outside their support;
- stamps are computed in ``stamp_dtype`` (float64 by default) and splatted in the images' dtype.

So the frames equal :func:`~weathergen.engine.render`'s up to float rounding (tested against it
in float64 to 1e-9 and in float32 to 1e-3, a quarter of a grey level). There is no backward
pass: this is for augmentation, where nothing is differentiated; attacks use
:func:`~weathergen.engine.render`.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..errors import ConfigError
from .compositing import upsample
from .particles import Particles
from .perframe import MAX_DEFOCUS, _smoothstep
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
        padded = [F.pad(lv[:, 0], (1, 1, 1, 1)).reshape(-1) for lv in levels]
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
    One host synchronisation for the whole layout (three when it is split into chunks)."""
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


def _packed(records: Sequence[Particles], device) -> tuple:
    """The records' particles concatenated in record order, copied to ``device`` in two
    tensors: ``reals`` (P, 18) float64 (position, motion, offset1, offset2, colour, θ, rotation,
    scale) and ``ints`` (P, 3) int64 (template, defocus, the record's index in ``records``)."""
    counts = [r.count for r in records]
    total = sum(counts)
    host = records[0].position.device

    def joined(name):
        return torch.cat([getattr(r, name).to(host) for r in records])

    reals = torch.cat([joined(f).to(torch.float64).view(total, 3 if i < 5 else 1)
                       for i, f in enumerate(_FLOAT_FIELDS + ("transparency", "rotation",
                                                               "scale"))], 1)
    record = torch.repeat_interleave(torch.arange(len(records), device=host),
                                     torch.tensor(counts, device=host), output_size=total)
    ints = torch.stack((joined("template").long(), joined("defocus").long(), record), 1)
    return reals.to(device), ints.to(device)


def _cameras(intrinsics, cam1_from_ref, cam2_from_ref, device) -> tuple:
    """Per view ``v = t B + b`` (frame t of pair b): ``K [R | t]`` (2B, 3, 4) and ``K R``
    (2B, 3, 3), float64."""
    k = intrinsics.to(device, torch.float64)
    k = torch.cat((k, k))
    cams = torch.cat((cam1_from_ref, cam2_from_ref)).to(device, torch.float64)[:, :3, :]
    full = k @ cams
    return full, full[:, :, :3]


def _homogeneous(matrix: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``matrix @ [points; 1]`` row by row. Shape: (N, 3, 4), (N, 3) -> (N, 3)."""
    return (matrix[:, :, :3] @ points[:, :, None])[:, :, 0] + matrix[:, :, 3]


def _step_groups(records: Sequence[Particles], dtype) -> dict:
    """Records grouped by their blur samples: ``{steps (tuple of floats): [record indices]}``."""
    groups: dict = {}
    for i, r in enumerate(records):
        groups.setdefault(tuple(_blur_steps(r, dtype, torch.device("cpu")).tolist()), []).append(i)
    return groups


def _members(groups: dict, record: torch.Tensor) -> list:
    """For each group of :func:`_step_groups`, which rows (of a table whose rows belong to the
    records ``record``) it holds: None for all (a single group)."""
    if len(groups) == 1:
        return [(steps, None) for steps in groups]
    out = []
    for steps, members in groups.items():
        chosen = torch.zeros(int(record.max()) + 1 if record.numel() else 1, dtype=torch.bool,
                             device=record.device)
        chosen[members] = True
        out.append((steps, torch.nonzero(chosen[record]).squeeze(1)))
    return out


def _paper_entries(records, pairs: list, views: tuple, lib, dtype, beta: float) -> tuple:
    """Stamps and tracks of records of the paper's model (fixed looks, one stamp per particle
    drawn in both frames of its pair ``pairs[i]``; the streak follows ``X2 − X1``, the apparent
    motion in camera coordinates). See :func:`_layout` for what is returned."""
    full, _ = views
    device = full.device
    bsz = full.shape[0] // 2
    reals, ints = _packed(records, device)
    template, defocus, record = ints.unbind(1)
    pair = torch.tensor(pairs, device=device)[record]
    flags = torch.tensor([bool(r.settings.defocus_brighten) for r in records], device=device)
    entries = dict(footprint=reals[:, 17] * lib.resolution, defocus=defocus,
                   rotation=reals[:, 16], template=template,
                   brighten=flags[record] & (defocus > 1), theta=reals[:, 15].to(dtype),
                   color=reals[:, 12:15].to(dtype))
    start = reals[:, 0:3] + reals[:, 6:9]
    end = start + reals[:, 3:6] + reals[:, 9:12]
    h1 = _homogeneous(full[pair], start)
    h2 = _homogeneous(full[bsz + pair], end)
    tracks = []
    for steps, rows in _members(_step_groups(records, dtype), record):
        pick = (lambda t: t) if rows is None else (lambda t: t[rows])  # noqa: E731
        entry = torch.arange(reals.shape[0], device=device) if rows is None else rows
        p = pick(pair)
        hd = pick(h2 - h1)
        tracks.append(dict(steps=steps, entry=torch.cat((entry, entry)),
                           view=torch.cat((p, bsz + p)), h0=torch.cat((pick(h1), pick(h2))),
                           hd=torch.cat((hd, hd)), beta=torch.full((2 * p.numel(),), beta,
                                                                   dtype=torch.float64,
                                                                   device=device)))
    return entries, tracks


def _field_entries(records, pairs: list, views: tuple, intrinsics, depths: torch.Tensor, lib,
                   dtype, beta: float) -> tuple:
    """Stamps and tracks of weather-field records: each particle is a candidate in both frames
    of its pair, and a frame draws it with its own looks, as
    :mod:`weathergen.engine.perframe` computes them (the view mask, footprint ``f d / z``, θ
    faded with depth and scaled by the area below one pixel, thin-lens defocus, occlusion
    softness), vectorised over every candidate. See :func:`_layout` for what is returned."""
    full, turn = views
    device = full.device
    bsz = full.shape[0] // 2
    height, width = depths.shape[-2:]
    reals, ints = _packed(records, device)
    n = reals.shape[0]
    template, _, record = ints.unbind(1)
    pair = torch.tensor(pairs, device=device)[record]
    optics = torch.tensor([[r.optics.near, r.optics.far, r.optics.fade, r.optics.aperture,
                            r.optics.focus, r.optics.depth_softness,
                            float(r.settings.blur_length), float(bool(r.settings.defocus_brighten))]
                           for r in records], dtype=torch.float64, device=device)
    k = intrinsics.to(device, torch.float64)
    focal = torch.sqrt(k[:, 0, 0] * k[:, 1, 1])
    start1 = reals[:, 0:3] + reals[:, 6:9]
    motion = reals[:, 3:6] + reals[:, 9:12]
    # candidates: every particle in frame 1, then in frame 2
    which = torch.cat((torch.arange(n, device=device),) * 2)
    rec = record[which]
    view = torch.cat((pair, bsz + pair))
    near, far, fade, aperture, focus, softness, blur, bright = optics[rec].unbind(1)
    f = torch.cat((focal, focal))[view]
    start = torch.cat((start1, start1 + motion))
    head = _homogeneous(full[view], start)                     # K X: (u z, v z, z)
    tail = _homogeneous(full[view], start + blur[:, None] * motion[which])
    z = head[:, 2]

    def blur_radius(depth):
        r = 0.5 * f * aperture * (1.0 / depth - 1.0 / focus).abs()
        return torch.where(aperture > 0, torch.floor(r.clamp(0, MAX_DEFOCUS) + 0.5),
                           torch.zeros_like(r))

    in_range = (z >= near) & (z <= far)
    safe = torch.where(in_range, z, far)
    reach = 0.5 * f * reals[which, 17] / safe + blur_radius(safe) + 2
    scene = depths.reshape(-1).to(torch.float64)

    def seen(h):
        """In front, reaching into the image, and not behind the scene at the nearest pixel."""
        zz = h[:, 2]
        zs = torch.where(zz.abs() > 1e-12, zz, torch.full_like(zz, 1e-12))
        u, v = h[:, 0] / zs, h[:, 1] / zs
        reaches = (zz > 1e-6) & (u >= -0.5 - reach) & (u <= width - 0.5 + reach) \
            & (v >= -0.5 - reach) & (v <= height - 0.5 + reach)
        col = torch.floor(u + 0.5).clamp(0, width - 1).long()
        row = torch.floor(v + 0.5).clamp(0, height - 1).long()
        return reaches & (zz <= scene[(view * height + row) * width + col] + 3 * softness)

    footprint = f * reals[which, 17] / z
    fade_out = torch.where(fade > 0, _smoothstep((far - z) / (fade * far)),
                           (z <= far).to(z.dtype))
    factor = _smoothstep((z - near) / near) * fade_out * footprint.clamp(max=1.0) ** 2
    kind = records[0].transparency.dtype            # θ is faded in the record's dtype
    theta = (reals[which, 15].to(kind) * factor.to(kind)).to(dtype)
    keep = torch.nonzero(in_range & (seen(head) | seen(tail)) & (theta != 0)).squeeze(1)
    defocus = blur_radius(z)[keep].long()
    drawn = which[keep]
    entries = dict(footprint=footprint[keep].clamp(min=1.0) / lib.resolution * lib.resolution,
                   defocus=defocus, rotation=reals[drawn, 16], template=template[drawn],
                   brighten=(bright[keep] > 0) & (defocus > 1), theta=theta[keep],
                   color=reals[drawn, 12:15].to(dtype))
    view, rec, h0 = view[keep], rec[keep], head[keep]
    hd = (turn[view] @ motion[drawn][:, :, None])[:, :, 0]            # K R (M + δ2)
    beta_view = torch.clamp(1.0 / softness[keep], max=beta)
    tracks = []
    for steps, rows in _members(_step_groups(records, dtype), rec):
        pick = (lambda t: t) if rows is None else (lambda t: t[rows])  # noqa: E731
        entry = torch.arange(keep.numel(), device=device) if rows is None else rows
        tracks.append(dict(steps=steps, entry=entry, view=pick(view), h0=pick(h0), hd=pick(hd),
                           beta=pick(beta_view)))
    return entries, tracks


def _layout(records, views, intrinsics, depths, lib, dtype, beta) -> tuple:
    """What the render call draws, as two tables:

    - *entries* (E,): one stamp each, ``footprint`` (pixels, float64), ``defocus`` (int64),
      ``rotation`` (float64), ``template``, ``brighten`` (bool), ``theta`` and ``color`` (E, 3)
      in the images' dtype: a particle of the paper's model is one entry drawn in both frames,
      a field particle one entry per frame that draws it;
    - *tracks*: a list of sets (one per distinct blur samples ``steps``) of tracks, each an
      entry's streak in one view: ``entry``, ``view`` (t B + b), ``h0`` and ``hd`` (float64
      (T, 3): the streak's start and direction in homogeneous image coordinates, ``K X`` and
      ``K ΔX``; the blur samples sit at ``h0 + s hd``), ``beta`` (the occlusion test's β).
    """
    paper = [i for i, r in enumerate(records) if r.optics is None and r.count]
    field = [i for i, r in enumerate(records) if r.optics is not None and r.count]
    parts = []
    if paper:
        parts.append(_paper_entries([records[i] for i in paper], paper, views, lib, dtype, beta))
    if field:
        parts.append(_field_entries([records[i] for i in field], field, views, intrinsics,
                                    depths, lib, dtype, beta))
    if not parts:
        return None, []
    entries = {key: torch.cat([e[key] for e, _ in parts]) for key in parts[0][0]}
    tracks, offset = [], 0
    for e, sets in parts:
        for t in sets:
            tracks.append(dict(t, entry=t["entry"] + offset))
        offset += int(e["template"].numel())
    return entries, tracks


class _Layout:
    """The stamps of a render call's entries (:func:`_layout`), with their geometry as the
    renderer computes it (:func:`~weathergen.engine.renderer.stamp_geometry`); all (E,)."""

    def __init__(self, entries: dict, lib: TemplateLibrary, stamp_dtype, coarse_side):
        self.template, self.theta, self.color = (entries[k] for k in ("template", "theta",
                                                                     "color"))
        self.count = int(self.template.numel())
        device = self.template.device
        if self.count and (int(self.template.min()) < 0 or int(self.template.max()) >= lib.count):
            raise ConfigError(f"particle template index out of range for the {lib.count} "
                              f"templates of '{lib.name}'")
        rotation = entries["rotation"].to(stamp_dtype)
        self.brighten = entries["brighten"]
        _, _, level_sides = _atlas(lib, stamp_dtype, device)
        footprint, radius, coarse, self.side, self.sub, self.level = stamp_geometry(
            entries["footprint"].clamp(min=1.0), entries["defocus"], lib.resolution,
            level_sides.numel(), coarse_side)
        self.radius, self.coarse = radius, coarse
        self.full_side = self.side + 2 * radius          # the stamp's side after its blur
        self.cos, self.sin = torch.cos(rotation), torch.sin(rotation)
        self.half = footprint.to(stamp_dtype) / 2


def _rasterise(lay: _Layout, lib: TemplateLibrary, stamp_dtype, chunk: int) -> tuple:
    """Every particle's stamp before its blur, ragged: ``(pixels (sum of side²,), first (P,))``.

    Each pixel averages ``sub x sub`` bilinear samples of the template's mip level at the rotated
    and scaled sample position, zero outside the footprint's disc (:func:`renderer._stamp_chunk`).
    """
    atlas, level_first, level_sides = _atlas(lib, stamp_dtype, lay.template.device)
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
    """Every entry's final stamp (disc-blurred where its radius is > 0, brightened where
    flagged), ragged with a one-pixel zero border: ``(stamps, first (E,))``, entry ``p``'s
    pixel ``(y, x)`` at ``first[p] + (y + 1) (S + 2) + x + 1`` with ``S = side + 2 radius``.

    The disc is a stack of rows ``dy`` of half-width ``w(dy)``: the blurred pixel ``(Y, X)``
    sums, over ``dy``, the stamp's row ``Y − r + dy`` between columns ``X − r ∓ w``. So every
    (entry, stamp row ``y``, disc row ``dy``) is a *segment* that adds the box sums of row ``y``
    (differences of its prefix sums) to the ``s + 2 w`` columns of output row ``y + r − dy`` it
    reaches; a stamp without blur (``r = 0``: one segment per row, ``w = 0``) is copied.
    """
    side, radius, full = lay.side, lay.radius, lay.full_side
    block = (full + 2) * (full + 2)
    out_first = torch.cumsum(block, 0) - block
    out = torch.zeros(int(block.sum()), dtype=pixels.dtype, device=pixels.device)
    prefix = torch.cat((pixels.new_zeros(1), torch.cumsum(pixels.to(torch.float64), 0)))
    rows = 2 * radius + 1
    for entry, local in _runs(side * rows, 1 << 62):             # the segments, all at once
        r, s = radius[entry], side[entry]
        y = torch.div(local, rows[entry], rounding_mode="floor")
        dy = local - y * rows[entry] - r
        w = torch.floor(torch.sqrt((r * r - dy * dy).to(torch.float64))).long()
        # per segment: where its stamp row starts, the output index of its first column
        # (X = r − w), 2 w, the row's last column, and whether the stamp is sharp
        segments = torch.stack((first[entry] + y * s,
                                out_first[entry] + (y + r - dy + 1) * (full[entry] + 2) + 1 + r - w,
                                2 * w, s - 1, (r == 0).long()), 1)
        for seg, x in _runs(s + 2 * w, chunk):
            start, at, w2, last, sharp = segments[seg].unbind(1)
            a = (x - w2).clamp(min=0)                  # columns a..b of the stamp row: never empty
            b = torch.minimum(x, last)
            value = torch.where(sharp > 0, pixels[start + b].to(prefix.dtype),
                                prefix[start + b + 1] - prefix[start + a])
            out.index_add_(0, at + x, value.to(out.dtype))
    sharp = radius == 0
    weight = torch.where(sharp, 1.0, 1.0 / _disc_counts(radius)).to(out.dtype)
    brighten = torch.stack((weight, lay.brighten.to(out.dtype)), 1)
    weight, brighten = torch.repeat_interleave(brighten, block, dim=0,
                                               output_size=out.numel()).unbind(1)
    out = out * weight
    out = torch.where(brighten > 0, defocus_brighten(out), out)
    return out, out_first


def _instances(lay: _Layout, tracks: list, dtype) -> dict:
    """Every track's blur samples, projected: flat tensors (I,) of ``u``, ``v``, ``z``,
    ``theta`` (the entry's θ / K), ``target`` (its view), ``particle`` (its entry), ``beta``,
    and ``color`` (I, 3)."""
    parts = []
    for t in tracks:
        k = len(t["steps"])
        n = t["entry"].numel()
        step = torch.tensor(t["steps"], dtype=torch.float64, device=t["h0"].device)
        pts = t["h0"][:, None, :] + step[:, None] * t["hd"][:, None, :]          # (T, K, 3)
        z = pts[..., 2]
        safe = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
        u, v = (pts[..., :2] / safe[..., None]).to(dtype).unbind(-1)

        def each(values):
            return values[:, None].expand(n, k, *values.shape[1:]).reshape(n * k, -1).squeeze(1)

        parts.append(dict(u=u.reshape(-1), v=v.reshape(-1), z=z.to(dtype).reshape(-1),
                          theta=each(lay.theta[t["entry"]] / k), target=each(t["view"]),
                          particle=each(t["entry"]), beta=each(t["beta"].to(dtype)),
                          color=each(lay.color[t["entry"]]).reshape(-1, 3)))
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
    """Render one particle record per pair, of the paper's model or sampled from a weather
    field, as :func:`~weathergen.engine.render` does (same arguments; the shapes and reference
    frames are the caller's to check, see :func:`weathergen.training.batchrender.render_records`),
    in a fixed number of tensor operations and without gradients (see the module doc).
    ``templates``: default, the library the records name. ``chunk_elements``: default
    :func:`chunk_elements_for` the device.

    Shape: images (B, 3, H, W), depths (B, 1, H, W), intrinsics (B, 3, 3), transforms
    (B, 4, 4); returns :class:`RenderOutput` with images (B, 3, H, W), opacities (B, 1, H, W).
    """
    templates = check_records(records, templates)
    bsz, _, height, width = image1.shape
    dtype, device = image1.dtype, image1.device
    if chunk_elements is None:
        chunk_elements = chunk_elements_for(device)
    with torch.no_grad():
        reached = torch.zeros(bsz, dtype=torch.bool, device=device)
        depths = torch.stack((depth1, depth2)).to(dtype).reshape(-1, 1, height, width)
        views = _cameras(intrinsics, cam1_from_ref, cam2_from_ref, device)
        entries, tracks = _layout(records, views, intrinsics, depths, templates, dtype,
                                  float(beta))
        acc = None
        if entries is not None:
            lay = _Layout(entries, templates, stamp_dtype, coarse_side)
        if entries is not None and lay.count:
            pixels, first = _rasterise(lay, templates, stamp_dtype, chunk_elements)
            stamps, first = _blur(lay, pixels, first, chunk_elements)
            inst = _instances(lay, tracks, dtype)
            acc = _splat(lay, stamps.to(dtype), first, inst, depths, chunk_elements, reached)
        return blend_sums(acc, image1, image2, records, reached)


def _splat(lay: _Layout, stamps, first, inst: dict, depths: torch.Tensor, chunk: int,
           reached: torch.Tensor) -> Optional[torch.Tensor]:
    """The per-pixel sums A, C_r, C_g, C_b of every blur sample's bilinearly shifted stamp times
    its visibility and θ / K, on every grid at once (full resolution, and the coarse grids of
    large billboards, whose sums are upsampled into the finer ones). Marks ``reached``.

    Each grid is drawn with a margin as wide as its largest patch, so a patch that hangs over the
    image's edge needs no bounds checks: what lands in the margin is cropped away.
    Shape: depths (2 B, 1, H, W) -> (4, 2 B H W), or None when no sample reaches a frame."""
    views, _, height, width = depths.shape
    device = depths.device
    # per grid level: whether it holds stamps, and its widest stamp (one synchronisation)
    top = COARSE_MAX_LEVEL + 1
    held = torch.stack((torch.bincount(lay.coarse, minlength=top),
                        torch.zeros(top, dtype=torch.long, device=device)
                        .scatter_reduce(0, lay.coarse, lay.full_side, "amax")))
    held = held.tolist()
    levels = [c for c in reversed(range(top)) if held[0][c]]
    pooled = _depth_levels(depths, [c for c in levels if c > 0])
    grids, offset, padded_depths = {}, 0, []
    for c in levels:
        f = 2 ** c
        h, w = (height, width) if c == 0 else (-(-height // f), -(-width // f))
        m = held[1][c] + 1                                   # the margin, pixels
        grids[c] = (offset, h, w, m)
        padded_depths.append(F.pad(depths if c == 0 else pooled[c], (m, m, m, m)).reshape(-1))
        offset += views * (h + 2 * m) * (w + 2 * m)
    scene = torch.cat(padded_depths)
    table = torch.tensor([[*grids.get(c, (0, 1, 1, 0)), 2 ** c] for c in range(top)],
                         device=device)
    geometry = torch.stack((lay.full_side, lay.coarse), 1)[inst["particle"]]
    side, coarse = geometry.unbind(1)
    start, h, w, m, f = table[coarse].unbind(1)                 # the particle's grid
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
    # per kept sample, gathered once per chunk: integers (the patch's side, the stamp's place
    # and row stride, the padded grid's row stride and the patch's first pixel in it) and reals
    # (sub-pixel shift, β, β z, and θ / K times the weights of A and C)
    row_stride = w + 2 * m
    corner = start + (target * (h + 2 * m) + v0.long() - half + m) * row_stride \
        + u0.long() - half + m
    ints = torch.stack((side + 1, side + 2, first[inst["particle"]], row_stride, corner), 1)[sel]
    theta = inst["theta"][:, None]
    reals = torch.cat((torch.stack((u - u0, v - v0, inst["beta"], inst["beta"] * inst["z"]), 1),
                       theta, theta * inst["color"]), 1)[sel]
    acc = torch.zeros(4, offset, dtype=stamps.dtype, device=device)
    for i, local in _runs(ints[:, 0] * ints[:, 0], chunk):
        n, stride, fst, grid_stride, corner = ints[i].unbind(1)
        here = reals[i]
        fu, fv, beta, beta_z = here[:, :4].unbind(1)
        row = torch.div(local, n, rounding_mode="floor")
        col = local - row * n
        # the bordered stamp's pixel (row, col) is the stamp's (row − 1, col − 1): the four
        # neighbours stamp[row − a, col − b] (a, b in {0, 1}) are always inside the block
        at = fst + row * stride + col
        top_row = torch.lerp(stamps[at + stride + 1], stamps[at + stride], fu)
        bottom = torch.lerp(stamps[at + 1], stamps[at], fu)
        value = torch.lerp(top_row, bottom, fv)
        pix = corner + row * grid_stride + col
        weight = value * torch.sigmoid(beta * scene[pix] - beta_z)
        acc.index_add_(1, pix, here[:, 4:].t() * weight)
    carry = None
    for k, c in enumerate(levels):
        start, h, w, m = grids[c]
        sums = acc[:, start:start + views * (h + 2 * m) * (w + 2 * m)] \
            .view(-1, 1, h + 2 * m, w + 2 * m)[..., m:m + h, m:m + w]
        if carry is not None:
            sums = sums + upsample(carry, 2 ** (levels[k - 1] - c), (h, w))
        carry = sums
    if levels[-1] > 0:
        carry = upsample(carry, 2 ** levels[-1], (height, width))
    return carry.reshape(4, -1)


__all__ = ["FLAT_CHUNK_ELEMENTS", "chunk_elements_for", "render_flat"]
