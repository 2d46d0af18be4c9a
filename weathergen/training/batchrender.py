"""Rendering the weather of a training batch in few device operations.

The renderer handles particles in buckets of equal stamp side, and each bucket costs a fixed
number of tensor operations (rasterising its stamps, planning and splatting its instances) on top
of its arithmetic. On a GPU these operations, each a kernel launch with its Python around it,
cost far more than the arithmetic of a training batch's weather, so the number of buckets sets
the time. Two ways to render a batch's paper-model records:

- **exact** (the default on the CPU): every record's stamps are rasterised on their own
  (:func:`stamps_per_record`), so each pair's pixels are bit for bit those of rendering it alone;
  the batch has as many buckets as its records have together.
- **fast** (the default on other devices): the stamps of all records are rasterised together
  (:func:`batch_stamps`; buckets shared by the records), in float64 and stored in float32, and the
  buckets are then merged into a few classes of side (:func:`coalesce_buckets`): a stamp is padded
  with zeros, centred, to its class's side. Zero-padded pixels add exactly nothing, so the frames
  are the exact path's up to the order of floating-point additions (CPU: within 1e-6, tested).
  Rasterising in float64 keeps the stamps free of the last-bit differences between devices and
  convolution algorithms (TF32, FFT-based) that the cube-root brightening of defocused stamps
  would otherwise magnify near zero.
"""

from __future__ import annotations

import functools
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from ..engine import BETA_RENDER, RenderOutput, StampSet, build_stamps, load_templates, render
from ..engine.presets import BLEND_MODES
from ..engine.renderer import (_SIDES, DEFAULT_CHUNK_ELEMENTS, StampBucket, _disc_kernel, _splat,
                               _stamp_chunk, mip_pyramid)
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
        buckets.extend(StampBucket(side=b.side, particles=b.particles + first, stamps=b.stamps)
                       for b in stamps.buckets)
        bucket_of.append(stamps.bucket_of + offset)
        slot_of.append(stamps.slot_of)
        first += record.count
    return StampSet(buckets=buckets, bucket_of=torch.cat(bucket_of), slot_of=torch.cat(slot_of))


def batch_stamps(records: Sequence, device=None, *, coalesce: bool = True,
                 dtype: torch.dtype = torch.float32, ratio: float = CLASS_RATIO) -> StampSet:
    """The stamps of all ``records`` (paper-model records sharing a template library), rasterised
    for the whole batch at once in float64 and stored in ``dtype``; with ``coalesce`` the buckets
    are the side classes of :func:`side_classes`, else one per final stamp side.

    The stamps are those of :func:`~weathergen.engine.build_stamps` (same footprint, stamp side,
    mip level, rotation, disc-blur radius and cube-root brightening) with fewer operations:
    templates are resampled once per (side, mip level) instead of once per bucket, and the disc
    blur of every radius is one FFT per side class (float64, values below 1e-12 dropped before the
    brightening, as the renderer does for its large stamps), with each stamp centred on its
    class's canvas. Equal to the renderer's stamps up to float rounding, tested.
    """
    library = load_templates(records[0].settings.templates)
    device = torch.device(device) if device is not None else records[0].device
    f64 = torch.float64
    with torch.no_grad():
        template = torch.cat([r.template for r in records]).to(device)
        rotation = torch.cat([r.rotation for r in records]).to(device=device, dtype=f64)
        footprint = torch.cat([r.scale for r in records]).to(device=device, dtype=f64)
        footprint = (footprint * library.resolution).clamp(min=1.0)
        radius = torch.cat([r.defocus for r in records]).to(device).long()
        radius = torch.where(radius > 1, radius, torch.zeros_like(radius))
        brighten = torch.cat([torch.full((r.count,), bool(r.settings.defocus_brighten))
                              for r in records]).to(device)
        count = int(template.numel())
        if count and (int(template.min()) < 0 or int(template.max()) >= library.count):
            raise ConfigError(f"particle template index out of range for the {library.count} "
                              f"templates of '{library.name}'")
        levels = mip_pyramid(library, f64, device)
        raw_side = 2 * torch.floor(footprint / 2).clamp(min=1).long() + 1
        sides = _SIDES.to(device)
        side = sides[torch.searchsorted(sides, raw_side)]
        level = torch.floor(torch.log2(library.resolution / footprint)).clamp(
            0, len(levels) - 1).long()
        final = side + 2 * radius
        # one host read for every grouping below
        table = torch.stack((side, level, final)).cpu()
        final_sides = torch.unique(table[2]).tolist()
        classes = side_classes(final_sides, ratio) if coalesce else {v: v for v in final_sides}
        lookup = torch.zeros(max(final_sides) + 1, dtype=torch.long)
        lookup[torch.tensor(list(classes))] = torch.tensor(list(classes.values()))
        canvas = lookup[table[2]]                                       # class side per particle
        # 1. resample the templates: one grid_sample per (side, level), onto the class canvas
        out = {c: None for c in sorted(set(classes.values()))}
        for c in out:
            n_c = int((canvas == c).sum())
            out[c] = torch.zeros(n_c, c, c, dtype=f64, device=device)
        slot = torch.zeros(count, dtype=torch.long)
        for c in out:
            members = torch.nonzero(canvas == c).squeeze(1)
            slot[members] = torch.arange(members.numel())
        slot_dev = slot.to(device)
        sl_key = table[0] * 64 + table[1]
        for key in torch.unique(sl_key).tolist():
            s, lvl = key // 64, key % 64
            members = torch.nonzero(sl_key == key).squeeze(1)
            per_chunk = max(1, DEFAULT_CHUNK_ELEMENTS // (s * s * 4))
            for start in range(0, members.numel(), per_chunk):
                m_cpu = members[start:start + per_chunk]
                m = m_cpu.to(device)
                stamp = _stamp_chunk(levels, lvl, template[m], rotation[m], footprint[m], s)
                for c in torch.unique(canvas[m_cpu]).tolist():
                    here = canvas[m_cpu] == c
                    pad = (c - s) // 2
                    rows = slot_dev[m[here.to(device)]]
                    out[c][rows, pad:pad + s, pad:pad + s] = stamp[here.to(device)]
        # 2. the disc blur of every radius, one FFT per class, for the stamps that have one
        buckets, first = [], {}
        radius_cpu = radius.cpu()
        for c, stamps in out.items():
            members = torch.nonzero(canvas == c).squeeze(1)
            blurred = torch.nonzero(radius_cpu[members] > 1).squeeze(1)
            if blurred.numel():
                radii = radius_cpu[members[blurred]]
                wanted = torch.unique(radii)
                kernels = torch.stack([_wrapped_disc(r, c) for r in wanted.tolist()])
                spectra = torch.fft.rfft2(kernels.to(device))
                which = torch.searchsorted(wanted, radii).to(device)
                rows = blurred.to(device)
                sharp = stamps[rows]
                soft = torch.fft.irfft2(torch.fft.rfft2(sharp) * spectra[which], s=(c, c))
                soft = torch.where(soft > 1e-12, soft, torch.zeros_like(soft))
                bright = brighten[members.to(device)[rows]][:, None, None]
                soft = torch.where(bright, soft.clamp(min=0).pow(1.0 / 3.0).clamp(0, 1), soft)
                stamps[rows] = soft
            first[c] = len(buckets)
            buckets.append(StampBucket(side=c, particles=members.to(device),
                                       stamps=stamps.to(dtype)))
        bucket_index = torch.zeros(max(out) + 1, dtype=torch.long)
        bucket_index[torch.tensor(list(first))] = torch.tensor(list(first.values()))
        bucket_of = bucket_index[canvas].to(device)
    return StampSet(buckets=buckets, bucket_of=bucket_of, slot_of=slot_dev)


@functools.lru_cache(maxsize=512)
def _wrapped_disc(radius: int, canvas: int) -> torch.Tensor:
    """The renderer's normalised disc PSF of ``radius`` on a ``canvas`` x ``canvas`` grid, centred
    on pixel (0, 0) and wrapping around (for a circular convolution). Shape: (canvas, canvas)."""
    disc = _disc_kernel(radius, torch.float64, "cpu")[0, 0]
    grown = F.pad(disc, (0, canvas - 2 * radius - 1, 0, canvas - 2 * radius - 1))
    return torch.roll(grown, (-radius, -radius), (0, 1))


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
    (:func:`side_classes`), the buckets of a class concatenated in their order.

    Shape: as :class:`StampSet`; a particle's stamp keeps its pixels at the centre of its new,
    larger stamp, so the splat adds the same values plus exact zeros.
    """
    if not stamps.buckets:
        return stamps
    classes = side_classes([b.side for b in stamps.buckets], ratio)
    order = sorted(set(classes.values()))
    members = {c: [] for c in order}
    for b, bucket in enumerate(stamps.buckets):
        members[classes[bucket.side]].append(b)
    device = stamps.bucket_of.device
    new_bucket = torch.empty(len(stamps.buckets), dtype=torch.long)
    first_slot = torch.empty(len(stamps.buckets), dtype=torch.long)
    buckets = []
    for c, side in enumerate(order):
        parts, particles, filled = [], [], 0
        for b in members[side]:
            bucket = stamps.buckets[b]
            pad = (side - bucket.side) // 2
            parts.append(F.pad(bucket.stamps, (pad, pad, pad, pad)) if pad else bucket.stamps)
            particles.append(bucket.particles)
            new_bucket[b], first_slot[b] = c, filled
            filled += int(bucket.stamps.shape[0])
        buckets.append(StampBucket(side=side, particles=torch.cat(particles),
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
    if exact:
        return render(pairs.image1, pairs.image2, pairs.depth1, pairs.depth2, pairs.intrinsics,
                      c1, c2, list(records), stamps=record_stamps(records, device, True,
                                                                  pairs.image1.dtype))
    return _render_fast(pairs, c1, c2, list(records))


def batch_instances(records: Sequence, intrinsics: torch.Tensor, cam1_from_ref: torch.Tensor,
                    cam2_from_ref: torch.Tensor, dtype, device) -> Optional[dict]:
    """The projected blur samples of all records, as the renderer's instance table, computed for
    the whole batch at once (the renderer's own loop goes record by record).

    Shape: intrinsics (B, 3, 3), cam*_from_ref (B, 4, 4), one record per pair. Returns a dict of
    flat tensors over the I instances: u, v (pixels), z (camera depth), theta (θ / K),
    color (I, 3), target (frame t * B + pair), particle (index into the records' concatenation);
    ``None`` when the records hold no particle.
    """
    bsz = len(records)
    counts = [r.count for r in records]
    if sum(counts) == 0:
        return None
    # one blur-step table per distinct number of samples K (usually one for the whole batch)
    by_k = {}
    for b, rec in enumerate(records):
        k = int(rec.settings.blur_samples) if rec.settings.blur_length > 0 else 1
        by_k.setdefault(max(k, 1), []).append(b)
    first = torch.tensor([0] + counts[:-1]).cumsum(0).tolist()
    cams = (cam1_from_ref.to(device=device, dtype=dtype), cam2_from_ref.to(device=device,
                                                                            dtype=dtype))
    kk = intrinsics.to(device=device, dtype=dtype)
    out = {key: [] for key in ("u", "v", "z", "theta", "color", "target", "particle")}
    for k, members in sorted(by_k.items()):
        members = [b for b in members if counts[b]]
        if not members:
            continue

        def cat(name):
            return torch.cat([getattr(records[b], name) for b in members]).to(device=device,
                                                                             dtype=dtype)

        n = torch.tensor([counts[b] for b in members])
        pair = torch.repeat_interleave(torch.tensor(members), n).to(device)            # (P,)
        particle = torch.cat([torch.arange(first[b], first[b] + counts[b])
                              for b in members]).to(device)
        # the renderer's blur steps: K fractions from 0 to the record's blur length
        steps = torch.stack([torch.linspace(0.0, float(records[b].settings.blur_length), k,
                                            dtype=dtype) if k > 1 else torch.zeros(1, dtype=dtype)
                             for b in members])
        steps = torch.repeat_interleave(steps, n, dim=0).to(device)                   # (P, K)
        start1 = cat("position") + cat("offset1")
        displacement = cat("motion") + cat("offset2")
        streak = steps[:, :, None] * displacement[:, None, :]                          # (P, K, 3)
        p = int(pair.numel())
        theta = (cat("transparency") / k)[:, None].expand(p, k).reshape(-1)
        color = cat("color")[:, None, :].expand(p, k, 3).reshape(-1, 3)
        fx, fy = kk[pair, 0, 0, None], kk[pair, 1, 1, None]
        cx, cy, skew = kk[pair, 0, 2, None], kk[pair, 1, 2, None], kk[pair, 0, 1, None]
        for t, start in enumerate((start1, start1 + displacement)):
            cam = cams[t][pair]                                                        # (P, 4, 4)
            # elementwise rather than a matrix product, which a training script's TF32
            # setting would round to 10 bits
            pts = (cam[:, None, :3, :3] * (start[:, None, :] + streak)[:, :, None, :]).sum(-1) \
                + cam[:, None, :3, 3]                                                  # (P, K, 3)
            z = pts[..., 2]
            safe = torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))
            x, y = pts[..., 0] / safe, pts[..., 1] / safe
            out["u"].append((fx * x + skew * y + cx).reshape(-1))
            out["v"].append((fy * y + cy).reshape(-1))
            out["z"].append(z.reshape(-1))
            out["theta"].append(theta)
            out["color"].append(color)
            out["target"].append((t * bsz + pair)[:, None].expand(p, k).reshape(-1))
            out["particle"].append(particle[:, None].expand(p, k).reshape(-1))
    return {key: torch.cat(v) for key, v in out.items()}


def _render_fast(pairs: FramePairBatch, c1: torch.Tensor, c2: torch.Tensor,
                 records: list) -> RenderOutput:
    """The fast path of :func:`render_records`: :func:`batch_instances`, :func:`batch_stamps` and
    the renderer's splat, blended as :func:`~weathergen.engine.render` blends."""
    image1, image2 = pairs.image1, pairs.image2
    dtype, device = image1.dtype, image1.device
    bsz, _, height, width = image1.shape
    library = load_templates(records[0].settings.templates)
    for r in records:
        if r.settings.templates != records[0].settings.templates or (
                r.settings.templates_digest and r.settings.templates_digest != library.digest):
            raise ConfigError(f"records of one batch render must share the templates they were "
                              f"sampled with; got '{r.settings.templates}' and "
                              f"'{records[0].settings.templates}'")
        if r.settings.blend not in BLEND_MODES:
            raise ConfigError(f"unknown blend mode {r.settings.blend!r}")
    acc = None
    inst = batch_instances(records, pairs.intrinsics, c1, c2, dtype, device)
    if inst is not None:
        stamps = batch_stamps(records, device, dtype=dtype)
        depth_flat = torch.stack((pairs.depth1, pairs.depth2)).to(dtype).reshape(-1)
        chunk = DEFAULT_CHUNK_ELEMENTS if device.type == "cpu" else DEVICE_CHUNK_ELEMENTS
        acc, _ = _splat(depth_flat, inst, stamps, height, width, BETA_RENDER, chunk)
    if acc is None:
        acc = [torch.zeros(2 * bsz * height * width, dtype=dtype, device=device)
               for _ in range(4)]
    alpha = acc[0].view(2, bsz, 1, height, width)
    colour = torch.stack([a.view(2, bsz, height, width) for a in acc[1:]], 2)
    images = torch.stack((image1, image2))
    alpha_mode = torch.tensor([r.settings.blend == "alpha" for r in records], device=device)
    out = torch.where(alpha_mode.view(1, bsz, 1, 1, 1), images * (1 - alpha) + colour,
                      images + colour).clamp(0, 1)
    opacity = alpha.clamp(0, 1)
    return RenderOutput(image1=out[0], image2=out[1], opacity1=opacity[0], opacity2=opacity[1])


__all__ = ["CLASS_RATIO", "DEVICE_CHUNK_ELEMENTS", "batch_instances", "batch_stamps",
           "coalesce_buckets", "record_stamps", "render_records", "side_classes",
           "stamps_per_record"]
