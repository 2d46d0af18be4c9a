"""Rendering the weather of a training batch: exactly as pair by pair, or in few device operations.

Two ways to render a batch of particle records (the paper's model, weather fields, or both):

- **exact** (the default on the CPU): the batch goes through :func:`~weathergen.engine.render`
  with every paper-model record's stamps rasterised on their own (:func:`stamps_per_record`;
  weather-field records take the renderer's per-frame path, one view at a time), so each pair's
  pixels are bit for bit those of rendering it alone. The renderer works in buckets of
  equal stamp side, a fixed set of tensor operations each (tens of thousands of operations for a
  batch of six Sintel-size pairs).
- **fast** (the default on other devices): :func:`~weathergen.engine.flat.render_flat`, the same
  models with the particles laid out ragged, in a few hundred tensor operations whatever the
  particles' number and sizes and whatever mix of models the batch holds. On a GPU every
  operation is a kernel launch with Python around it, and their number, not their arithmetic,
  sets the time of a batch's weather. The frames equal the exact
  path's up to float rounding (stamps in float64; tested to 1e-9 in float64 and 1e-3, a quarter
  of a grey level, in float32).
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import torch

from ..engine import RenderOutput, StampSet, build_stamps, load_templates, render
from ..engine.flat import render_flat
from ..errors import ConfigError
from ..framepair import FramePairBatch


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


def render_records(pairs: FramePairBatch, records: Sequence, *, exact: Optional[bool] = None
                   ) -> RenderOutput:
    """Render one particle record per pair of ``pairs`` (of the paper's model or sampled from a
    weather field) on the pairs' device: with
    ``exact`` (default: on the CPU) through :func:`~weathergen.engine.render` with the stamps of
    :func:`stamps_per_record` (field records: the renderer's per-frame path), else with
    :func:`~weathergen.engine.flat.render_flat` (see the module doc). Same reference frames and
    checks as :func:`~weathergen.engine.render_pair`.
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
    if not exact:
        return render_flat(pairs.image1, pairs.image2, pairs.depth1, pairs.depth2,
                           pairs.intrinsics, c1, c2, list(records))
    # weather-field records are drawn view by view with looks computed per frame (no prebuilt
    # stamps); the renderer gives each pair's paper-model record its own call there
    per_frame = any(r.optics is not None for r in records)
    stamps = None if per_frame else stamps_per_record(records, device, pairs.image1.dtype)
    return render(pairs.image1, pairs.image2, pairs.depth1, pairs.depth2, pairs.intrinsics, c1, c2,
                  list(records), stamps=stamps)


__all__ = ["render_records", "stamps_per_record"]
