"""Rendering the weather of a training batch in few device operations.

The renderer handles particles in buckets of equal stamp side (and mip level, defocus radius,
grid), and each bucket costs a fixed number of tensor operations (rasterising its stamps,
planning and splatting its instances) on top of its arithmetic. On a GPU these operations, each
a kernel launch with its Python around it, cost far more than the arithmetic of a training
batch's weather, so the number of buckets sets the time. Two ways to render a batch of
paper-model records:

- **exact** (the default on the CPU): every record's stamps are rasterised on their own
  (:func:`stamps_per_record`), so each pair's pixels are bit for bit those of rendering it alone;
  the batch has as many buckets as its records have together.
- **fast** (the default on other devices): the stamps of all records are rasterised in one call
  of the renderer's :func:`~weathergen.engine.build_stamps` (buckets shared by the records), and
  the buckets of each grid are then merged into a few classes of side (:func:`coalesce_buckets`):
  a stamp is padded with zeros, centred, to its class's side. Zero-padded pixels add exactly
  nothing, so on the CPU the frames are the exact path's up to the order of floating-point
  additions (within 1e-5, tested). Off the CPU the stamps are rasterised in float64 (and stored
  in the images' dtype): the GPU's convolution algorithms (TF32, FFT-based) round the defocus
  blur coarsely, and the brightening of defocused stamps (a cube root) magnifies that near zero.
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..engine import RenderOutput, StampSet, build_stamps, load_templates, render
from ..engine.renderer import DEFAULT_CHUNK_ELEMENTS
from ..errors import ConfigError
from ..framepair import FramePairBatch

#: Patch pixels splatted per chunk off the CPU in the fast path (a few hundred MiB of temporaries;
#: the CPU keeps the renderer's default, which suits its caches).
DEVICE_CHUNK_ELEMENTS = 1 << 23
#: Buckets whose stamp sides lie within this factor of the class's smallest side share a class
#: (at most about this factor squared more pixels per stamp, for a few classes in all).
CLASS_RATIO = 1.5


def stamps_per_record(records: Sequence, device=None, dtype: torch.dtype = torch.float32
                      ) -> StampSet:
    """The stamps of several particle records, rasterised record by record and put together.

    Rasterising every record on its own makes each pair's pixels independent of the other pairs
    in the batch (the defocus blur is a batched convolution whose last bits depend on how many
    stamps it convolves at once), so the batched render equals the per-pair render bit for bit on
    the CPU.
    """
    library = load_templates(records[0].settings.templates)
    buckets, bucket_of, slot_of, first = [], [], [], 0
    for record in records:
        stamps = build_stamps([record], library, dtype=dtype, device=device)
        offset = len(buckets)
        buckets.extend(dataclasses.replace(b, particles=b.particles + first)
                       for b in stamps.buckets)
        bucket_of.append(stamps.bucket_of + offset)
        slot_of.append(stamps.slot_of)
        first += record.count
    return StampSet(buckets=buckets, bucket_of=torch.cat(bucket_of), slot_of=torch.cat(slot_of))


def batch_stamps(records: Sequence, device=None, *, coalesce: bool = True,
                 dtype: torch.dtype = torch.float32, ratio: float = CLASS_RATIO) -> StampSet:
    """The stamps of all ``records`` from one rasterisation (buckets shared by the records),
    computed in ``dtype`` on the CPU and in float64 elsewhere (see the module doc), stored in
    ``dtype``; with ``coalesce``, merged into side classes (:func:`coalesce_buckets`)."""
    library = load_templates(records[0].settings.templates)
    device = torch.device(device) if device is not None else records[0].device
    work = dtype if device.type == "cpu" else torch.float64
    stamps = build_stamps(records, library, dtype=work, device=device)
    stamps = StampSet(buckets=[dataclasses.replace(b, stamps=b.stamps.to(dtype))
                               for b in stamps.buckets],
                      bucket_of=stamps.bucket_of, slot_of=stamps.slot_of)
    return coalesce_buckets(stamps, ratio) if coalesce else stamps


def side_classes(sides: Sequence[int], ratio: float = CLASS_RATIO) -> dict:
    """The class side of every stamp side: sides sorted, a class opened at the smallest side not
    yet covered, holding the sides up to ``ratio`` times it; its side is the largest it holds
    (sides are odd, so a stamp pads to it symmetrically). Returns ``{side: class side}``."""
    out, group = {}, []
    for s in sorted(set(int(v) for v in sides)):
        if group and s > ratio * group[0]:
            out.update({g: group[-1] for g in group})
            group = []
        group.append(s)
    out.update({g: group[-1] for g in group})
    return out


def coalesce_buckets(stamps: StampSet, ratio: float = CLASS_RATIO) -> StampSet:
    """The same stamps in fewer buckets: each stamp zero-padded (centred) to its side class
    (:func:`side_classes`, among the buckets of its grid: full resolution or one of the coarse
    grids of large billboards), the buckets of a class concatenated in their order.

    Shape: as :class:`StampSet`; a particle's stamp keeps its pixels at the centre of its new,
    larger stamp, so the splat adds the same values plus exact zeros.
    """
    if not stamps.buckets:
        return stamps
    groups = {}                      # (grid, class side) -> the old buckets it holds, in order
    for grid in sorted({b.coarse for b in stamps.buckets}):
        here = [i for i, b in enumerate(stamps.buckets) if b.coarse == grid]
        classes = side_classes([stamps.buckets[i].side for i in here], ratio)
        for i in here:
            groups.setdefault((grid, classes[stamps.buckets[i].side]), []).append(i)
    device = stamps.bucket_of.device
    new_bucket = torch.empty(len(stamps.buckets), dtype=torch.long)
    first_slot = torch.empty(len(stamps.buckets), dtype=torch.long)
    buckets = []
    for c, ((grid, side), members) in enumerate(groups.items()):
        parts, particles, filled = [], [], 0
        for b in members:
            bucket = stamps.buckets[b]
            pad = (side - bucket.side) // 2
            parts.append(F.pad(bucket.stamps, (pad, pad, pad, pad)) if pad else bucket.stamps)
            particles.append(bucket.particles)
            new_bucket[b], first_slot[b] = c, filled
            filled += int(bucket.stamps.shape[0])
        buckets.append(dataclasses.replace(
            stamps.buckets[members[0]], side=side, particles=torch.cat(particles),
            stamps=torch.cat(parts) if len(parts) > 1 else parts[0]))
    new_bucket, first_slot = new_bucket.to(device), first_slot.to(device)
    return StampSet(buckets=buckets, bucket_of=new_bucket[stamps.bucket_of],
                    slot_of=first_slot[stamps.bucket_of] + stamps.slot_of)


def record_stamps(records: Sequence, device, exact: Optional[bool] = None,
                  dtype: torch.dtype = torch.float32) -> StampSet:
    """The stamps a batch of paper-model records is rendered with, in ``dtype`` (the images'):
    :func:`stamps_per_record` when ``exact`` (default: on the CPU), else :func:`batch_stamps`."""
    device = torch.device(device)
    if exact is None:
        exact = device.type == "cpu"
    if exact:
        return stamps_per_record(records, device=device, dtype=dtype)
    return batch_stamps(records, device, dtype=dtype)


def render_records(pairs: FramePairBatch, records: Sequence, *, exact: Optional[bool] = None
                   ) -> RenderOutput:
    """Render one paper-model record per pair of ``pairs`` on the pairs' device, with the stamps
    of :func:`record_stamps` (``exact`` as there); the fast path off the CPU splats in chunks of
    :data:`DEVICE_CHUNK_ELEMENTS`. Same reference frames and checks as
    :func:`~weathergen.engine.render_pair`.
    Shape: ``pairs`` images (B, 3, H, W); returns images (B, 3, H, W), opacities (B, 1, H, W).
    """
    device = pairs.image1.device
    if exact is None:
        exact = device.type == "cpu"
    bsz = pairs.image1.shape[0]
    if pairs.cam1_from_world is not None and pairs.cam2_from_world is not None:
        c1, c2, frame = pairs.cam1_from_world, pairs.cam2_from_world, "world"
    else:
        c1 = torch.eye(4, dtype=torch.float64, device=device).expand(bsz, 4, 4)
        c2, frame = pairs.cam2_from_cam1, "camera1"
    for rec in records:
        if rec.frame != frame:
            raise ConfigError(f"particles live in {rec.frame} coordinates but the frame pair "
                              f"offers {frame} coordinates (sample them for this pair)")
    chunk = DEFAULT_CHUNK_ELEMENTS if exact or device.type == "cpu" else DEVICE_CHUNK_ELEMENTS
    return render(pairs.image1, pairs.image2, pairs.depth1, pairs.depth2, pairs.intrinsics, c1, c2,
                  list(records), stamps=record_stamps(records, device, exact, pairs.image1.dtype),
                  chunk_elements=chunk)


__all__ = ["CLASS_RATIO", "DEVICE_CHUNK_ELEMENTS", "batch_stamps", "coalesce_buckets",
           "record_stamps", "render_records", "side_classes", "stamps_per_record"]
