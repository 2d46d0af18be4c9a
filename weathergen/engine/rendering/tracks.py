"""Stage 1 of the render core: particle records and cameras -> what every view draws.

Both weather models end in the same drawing problem; they differ only in where the numbers of a
particle's drawing come from. This stage computes those numbers and nothing else:

- :class:`Looks`, one row per *stamp entry*: footprint (pixels), defocus radius, rotation,
  template, brightening. A particle of the paper's model is one entry, the same in both frames of
  its pair (looks fixed at sampling). A particle of a weather field (``optics`` set) is one entry
  per view that draws it, with that view's looks: footprint ``f d / z``, thin-lens defocus,
  depth fade, the view mask (see :func:`field_looks`). Per-frame looks are rows of this table,
  not a second renderer.
- :class:`Tracks`, one row per (entry, view): the streak in homogeneous image coordinates
  (``h0``, ``hd``: blur sample ``k`` sits at ``h0 + k · spacing · hd``), the number of blur
  samples, θ, colour and the occlusion sharpness β. The paper's streaks follow ``X2 − X1`` (both
  cameras of the pair); a field's (and a single view's) follow the particle's own displacement.
- :class:`Instances` (:func:`blur_samples`): every track's blur samples, projected: the input of
  the splat. The number of samples is a per-track column, adapted to the streak's length in
  pixels in each view (:func:`streak_samples`: consecutive samples at most one pixel apart, or
  as far apart as the stamp is smooth, up to :data:`MAX_BLUR_SAMPLES`).

Every geometric product is an elementwise product and a sum over the last axis (no matrix
products), so that a track's numbers do not depend on how many other tracks the call holds
(batched matrix kernels may sum in another order for another batch size).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from ..common import NEAR
from ..records.particles import Particles
from ..views import (OpticsRows, Views, detached, direction, fade, field_mask_looks,
                     homogeneous, scalar)

# -- records, looks and tracks -----------------------------------------------------------------

@dataclass
class ParticleTable:
    """The particles of several records, concatenated in record order (P particles).

    Shape: start (P, 3) float64 ``P + δ1`` and displacement (P, 3) float64 ``M + δ2``
    (differentiable in the offsets); color (P, 3), transparency (P,) as the records hold them
    (differentiable); rotation, scale (P,) float64; template, defocus, record (P,) int64.
    """

    start: torch.Tensor
    displacement: torch.Tensor
    color: torch.Tensor
    transparency: torch.Tensor
    rotation: torch.Tensor
    scale: torch.Tensor
    template: torch.Tensor
    defocus: torch.Tensor
    record: torch.Tensor

    @classmethod
    def of(cls, records: Sequence[Particles], device) -> "ParticleTable":
        def cat(name, dtype=None):
            t = torch.cat([getattr(r, name).to(device) for r in records])
            return t if dtype is None else t.to(dtype)

        f64 = torch.float64
        counts = torch.tensor([r.count for r in records], device=device)
        total = sum(r.count for r in records)
        vectors = [getattr(r, k) for k in ("position", "offset1", "motion", "offset2")
                   for r in records]
        if len({v.dtype for v in vectors}) == 1:    # (the usual case: all four in one cat)
            position, offset1, motion, offset2 = torch.cat([v.to(device) for v in vectors]) \
                .to(f64).view(4, total, 3).unbind(0)
            start, displacement = position + offset1, motion + offset2
        else:
            start = cat("position", f64) + cat("offset1", f64)
            displacement = cat("motion", f64) + cat("offset2", f64)
        return cls(start=start, displacement=displacement,
                   color=cat("color"), transparency=cat("transparency"),
                   rotation=cat("rotation", f64), scale=cat("scale", f64),
                   template=cat("template", torch.long), defocus=cat("defocus", torch.long),
                   record=torch.repeat_interleave(counts, output_size=total))

    @property
    def count(self) -> int:
        return int(self.record.numel())

    def select(self, rows: torch.Tensor) -> "ParticleTable":
        return ParticleTable(**{k: getattr(self, k)[rows] for k in self.__dataclass_fields__})

    def head(self, n: int) -> "ParticleTable":
        """The first n particles (views)."""
        return ParticleTable(**{k: getattr(self, k)[:n] for k in self.__dataclass_fields__})


#: The diameter of the disc of a unit square's area: a ``research`` record's footprint is this
#: times the whole pixels of the research code's resampled flake (see :func:`fixed_looks`).
RESEARCH_DISC = 2 / math.sqrt(math.pi)


@dataclass
class Looks:
    """How each stamp entry looks (E entries). Shape: footprint (E,) float64 pixels (>= 1);
    defocus (E,) int64 disc radius in pixels; rotation (E,) float64 radians; template (E,)
    int64; brighten (E,) bool (the disc-blurred alpha b becomes ``min(1, (2 b)^(1/3))``);
    coarse (E,) bool, whether a large stamp may be drawn on a coarser grid (its record's
    ``coarse`` setting; None: every entry may); research (E,) bool, whether its stamp is made
    as the research code makes it (its record's ``stamp_style``; None: none is)."""

    footprint: torch.Tensor
    defocus: torch.Tensor
    rotation: torch.Tensor
    template: torch.Tensor
    brighten: torch.Tensor
    coarse: Optional[torch.Tensor] = None
    research: Optional[torch.Tensor] = None

    @property
    def count(self) -> int:
        return int(self.template.numel())

    def may_be_coarse(self) -> torch.Tensor:
        """``coarse``, all true where not given. Shape: (E,) bool."""
        return self.coarse if self.coarse is not None \
            else torch.ones_like(self.brighten, dtype=torch.bool)

    def select(self, rows: torch.Tensor) -> "Looks":
        return Looks(**{k: None if getattr(self, k) is None else getattr(self, k)[rows]
                        for k in Looks.__dataclass_fields__})

    @staticmethod
    def cat(parts: Sequence["Looks"]) -> "Looks":
        fields = {k: torch.cat([getattr(p, k) for p in parts])
                  for k in Looks.__dataclass_fields__ if k not in ("coarse", "research")}
        if any(p.coarse is not None for p in parts):
            fields["coarse"] = torch.cat([p.may_be_coarse() for p in parts])
        if any(p.research is not None for p in parts):
            fields["research"] = torch.cat([torch.zeros_like(p.brighten) if p.research is None
                                            else p.research for p in parts])
        return Looks(**fields)


@dataclass
class Tracks:
    """T tracks, each an entry's streak in one view.

    Shape: entry, view (T,) int64 (into :class:`Looks`, :class:`Views`); h0, hd (T, 3) float64
    homogeneous pixels (``K X`` of the streak's start and ``K ΔX`` of its direction; blur sample
    ``k`` sits at ``h0 + k · spacing · hd``), differentiable in the offsets; samples (T,) int64
    the number K of blur samples; spacing (T,) float64; theta (T,) and color (T, 3) in the
    images' dtype, differentiable (each sample carries θ / K); beta (T,) float64, the occlusion
    test's sharpness.
    """

    entry: torch.Tensor
    view: torch.Tensor
    h0: torch.Tensor
    hd: torch.Tensor
    samples: torch.Tensor
    spacing: torch.Tensor
    theta: torch.Tensor
    color: torch.Tensor
    beta: torch.Tensor

    @property
    def count(self) -> int:
        return int(self.entry.numel())

    @staticmethod
    def cat(parts: Sequence["Tracks"], entry_offsets: Sequence[int]) -> "Tracks":
        """Tracks of several parts, each part's entries shifted by its offset."""
        fields = {k: torch.cat([getattr(p, k) for p in parts]) for k in Tracks.__dataclass_fields__
                  if k != "entry"}
        return Tracks(entry=torch.cat([p.entry + o for p, o in zip(parts, entry_offsets)]),
                      **fields)


@dataclass
class RecordRows:
    """Per-record settings as tensors (R records). Shape: samples (R,) int64 (K: 1 without motion
    blur); spacing (R,) float64 (``blur_length / (K − 1)``, 0 for K = 1); blur_length (R,)
    float64; brighten (R,) bool; optics (R, 7) float64 (near, far, fade, aperture, focus,
    depth_softness, zeros for the paper's records; then blur_length again: every number a
    field record's candidates read, gathered at once); coarse (R,) bool (large stamps may be
    drawn on a coarser grid); research (R,) bool (stamps made as the research code makes them;
    None where no record's are).
    """

    samples: torch.Tensor
    spacing: torch.Tensor
    blur_length: torch.Tensor
    brighten: torch.Tensor
    optics: torch.Tensor
    coarse: torch.Tensor
    research: Optional[torch.Tensor]

    @classmethod
    def of(cls, records: Sequence[Particles], device) -> "RecordRows":
        samples, spacing, length, bright, optics, coarse, research = [], [], [], [], [], [], []
        for r in records:
            s = r.settings
            k = int(s.blur_samples) if int(s.blur_samples) > 1 and s.blur_length > 0 else 1
            samples.append(k)
            spacing.append(float(s.blur_length) / (k - 1) if k > 1 else 0.0)
            length.append(float(s.blur_length))
            bright.append(bool(s.defocus_brighten))
            coarse.append(bool(s.coarse))
            research.append(s.stamp_style == "research")
            o = r.optics
            optics.append([0.0] * 6 + [length[-1]] if o is None else
                          [o.near, o.far, o.fade, o.aperture, o.focus, o.depth_softness,
                           length[-1]])
        f64 = torch.float64
        return cls(samples=torch.tensor(samples, device=device),
                   spacing=torch.tensor(spacing, dtype=f64, device=device),
                   blur_length=torch.tensor(length, dtype=f64, device=device),
                   brighten=torch.tensor(bright, device=device),
                   optics=torch.tensor(optics, dtype=f64, device=device).view(-1, 7),
                   coarse=torch.tensor(coarse, dtype=torch.bool, device=device),
                   research=torch.tensor(research, dtype=torch.bool, device=device)
                   if any(research) else None)


def fixed_looks(table: ParticleTable, rows: RecordRows, resolution: int) -> Looks:
    """The paper's model: looks fixed at sampling (footprint ``scale`` x template pixels; for a
    ``research`` record the disc of the area of the ``n x n`` window, n = floor(footprint),
    into which the research code resamples its flakes, :data:`RESEARCH_DISC` n, at most the
    footprint itself)."""
    footprint = table.scale * resolution
    research = None if rows.research is None else rows.research[table.record]
    if research is not None:
        window = torch.minimum(footprint.floor() * RESEARCH_DISC, footprint)
        footprint = torch.where(research, window, footprint)
    footprint = footprint.clamp(min=1.0)
    return Looks(footprint=footprint, defocus=table.defocus,
                 rotation=table.rotation, template=table.template,
                 brighten=rows.brighten[table.record] & (table.defocus > 1),
                 coarse=rows.coarse[table.record], research=research)


def field_looks(table: ParticleTable, which: torch.Tensor, rows: RecordRows, views: Views,
                view: torch.Tensor, start: torch.Tensor, *, beta: float, dtype: torch.dtype,
                color: Optional[torch.Tensor] = None, first_entry: int = 0
                ) -> tuple[Looks, Tracks]:
    """A weather field's particles as the views ``view`` (C,) see them, candidate ``c`` being
    particle ``which[c]`` of ``table`` seen from ``start[c]`` (C, 3; its reference position in
    that view's frame): the
    candidates the view mask keeps become one entry and one track each, with footprint
    ``f d / z`` (at least one pixel; below it θ is scaled by the footprint's area), θ faded with
    depth, a thin-lens defocus disc (light spread, not brightened) and ``β = min(beta,
    1 / depth_softness)``. Looks depend on the detached positions; the track's positions keep
    their gradient. The tracks' entries are numbered from ``first_entry`` on."""
    record = table.record.index_select(0, which)
    near, far, fraction, aperture, focus, softness, length = \
        rows.optics.index_select(0, record).unbind(1)
    project = views.project.index_select(0, view)
    f = views.focal.index_select(0, view)
    displacement = table.displacement.index_select(0, which)
    scale = table.scale.index_select(0, which)
    streak = length[:, None] * detached(displacement)
    mask, z, radius, fp, h0 = field_mask_looks(project, f, start, streak, scale,
                                          OpticsRows(near, far, fraction, aperture, focus,
                                                     softness), views.depth, view)
    factor = fade(near, far, fraction, z) * fp.clamp(max=1.0) ** 2
    theta = (table.transparency.index_select(0, which).to(torch.float64) * factor).to(dtype)
    keep = torch.nonzero(mask & (detached(theta) != 0)).squeeze(1)
    drawn, record, radius, view = torch.stack((which, record, radius, view)) \
        .index_select(1, keep).unbind(0)
    looks = Looks(footprint=fp.index_select(0, keep).clamp(min=1.0), defocus=radius,
                  rotation=table.rotation.index_select(0, drawn),
                  template=table.template.index_select(0, drawn),
                  brighten=rows.brighten.index_select(0, record) & (radius > 1),
                  coarse=rows.coarse.index_select(0, record))
    colour = table.color if color is None else color
    tracks = Tracks(entry=torch.arange(first_entry, first_entry + keep.numel(),
                                       device=keep.device),
                    view=view, h0=h0.index_select(0, keep),
                    hd=direction(project, displacement).index_select(0, keep),
                    samples=rows.samples.index_select(0, record),
                    spacing=rows.spacing.index_select(0, record),
                    theta=theta.index_select(0, keep), color=colour.index_select(0, drawn).to(dtype),
                    beta=torch.clamp(torch.reciprocal(softness.index_select(0, keep)), max=beta))
    return looks, tracks


def pair_tracks(records: Sequence[Particles], views: Views, resolution: int, *, beta: float,
                dtype: torch.dtype, pairs: Optional[Sequence[int]] = None
                ) -> tuple[Looks, Tracks]:
    """Looks and tracks of particle records drawn into frame pairs: record ``i`` into pair
    ``pairs[i]`` (default ``i``), whose frames are views ``p`` and ``B + p`` (B = V / 2).

    Entries: the paper's particles first, in record order (one entry each, drawn in both frames:
    its streak runs along ``X2 − X1``, frame t's from ``X_t``), then the field particles each
    view draws (frame 1 from ``P + δ1``, frame 2 from ``P + δ1 + M + δ2``, both along
    ``M + δ2``).
    """
    device = views.project.device
    bsz = views.count // 2
    pairs = list(range(len(records))) if pairs is None else list(pairs)
    paper = [i for i, r in enumerate(records) if r.optics is None and r.count]
    field = [i for i, r in enumerate(records) if r.optics is not None and r.count]
    if not paper and not field:
        return empty_looks(device), empty_tracks(device, dtype)
    # one table, the paper's records first: their particles are rows 0 .. n - 1
    order = paper + field
    chosen = [records[i] for i in order]
    table = ParticleTable.of(chosen, device)
    rows = RecordRows.of(chosen, device)
    pair = torch.tensor([pairs[i] for i in order], device=device).index_select(0, table.record)
    n = sum(records[i].count for i in paper)
    # every column's pieces, the paper's tracks (both frames) first, concatenated once
    columns: dict = {k: [] for k in Tracks.__dataclass_fields__}
    entries = []
    if paper:
        head = table if n == table.count else table.head(n)
        entries.append(fixed_looks(head, rows, resolution))
        for key, pieces in _paper_columns(head, rows, views, pair[:n], beta=beta,
                                          dtype=dtype).items():
            columns[key] += pieces
    if field:
        # every field particle is a candidate in both frames of its pair
        which = torch.arange(n, table.count, device=device).repeat(2)
        p = pair[n:]
        start = table.start[n:]
        looks, tracks = field_looks(table, which, rows, views, torch.cat((p, bsz + p)),
                                    torch.cat((start, start + table.displacement[n:])),
                                    beta=float(beta), dtype=dtype, first_entry=n)
        entries.append(looks)
        for key in columns:
            columns[key].append(getattr(tracks, key))
    looks = entries[0] if len(entries) == 1 else Looks.cat(entries)
    return looks, Tracks(**{k: v[0] if len(v) == 1 else torch.cat(v) for k, v in columns.items()})


def _paper_columns(head: ParticleTable, rows: RecordRows, views: Views, p: torch.Tensor, *,
                   beta: float, dtype: torch.dtype) -> dict[str, list]:
    """The tracks of the paper's particles ``head`` (the first n rows of the call's table, entries
    0 .. n − 1) in both frames of their pairs ``p`` (n,): frame 1 from ``X1``, frame 2 from
    ``X2``, both along ``X2 − X1``. Returns each :class:`Tracks` column's pieces, frame 1's rows
    then frame 2's (2 n rows in all)."""
    n, device = head.count, p.device
    start, record = head.start, head.record
    # both frames at once: frame 1 from X1, frame 2 from X2 (the first n rows, the last n)
    view = torch.cat((p, views.count // 2 + p))
    h = homogeneous(views.project.index_select(0, view),
                    torch.cat((start, start + head.displacement)))
    hd = h[n:] - h[:n]
    entry = torch.arange(n, device=device)
    samples = rows.samples.index_select(0, record)
    spacing = rows.spacing.index_select(0, record)
    theta, colour = head.transparency.to(dtype), head.color.to(dtype)
    columns = {"view": [view], "h0": [h],
               "beta": [torch.full((2 * n,), float(beta), dtype=torch.float64, device=device)]}
    for key, piece in (("entry", entry), ("hd", hd), ("samples", samples),
                       ("spacing", spacing), ("theta", theta), ("color", colour)):
        # (a differentiable piece repeated: its gradient is then the sum of both frames' in
        # the order of repeat's backward, to the sign of a zero)
        columns[key] = [piece.repeat(2, *[1] * (piece.dim() - 1))] \
            if piece.requires_grad else [piece, piece]
    return columns


def pair_starts(record: Particles, dtype, device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference positions in frames 1 and 2 and the displacement of a pair's record,
    ``P + δ1``, ``P + δ1 + M + δ2`` and ``M + δ2``. Shape: (N, 3) each."""
    pos = record.position.to(device=device, dtype=dtype)
    start1 = pos + record.offset1.to(device=device, dtype=dtype)
    displacement = record.motion.to(device=device, dtype=dtype) \
        + record.offset2.to(device=device, dtype=dtype)
    return start1, start1 + displacement, displacement


def view_tracks(record: Particles, views: Views, start: torch.Tensor, displacement: torch.Tensor,
                resolution: int, *, beta: float, dtype: torch.dtype,
                color: Optional[torch.Tensor] = None, kept: bool = False):
    """Looks and tracks of one record drawn into a single view (view 0 of ``views``): every
    particle from ``start`` (N, 3) along ``displacement`` (N, 3) (reference frame). A field
    record gets the view's looks (:func:`field_looks`); a record of the paper's model keeps its
    looks and draws the particles whose start lies in front of the camera. ``color`` (N, 3)
    replaces the colour (e.g. by flow vectors). With ``kept``, also the indices (M,) of the
    particles drawn, for a record of the paper's model (whose entries are those particles)."""
    device = views.project.device
    if record.count == 0:
        empty = (empty_looks(device), empty_tracks(device, dtype))
        return (*empty, torch.zeros(0, dtype=torch.long, device=device)) if kept else empty
    table = ParticleTable.of([record], device)
    table.start = start.to(device=device, dtype=torch.float64)
    table.displacement = displacement.to(device=device, dtype=torch.float64)
    rows = RecordRows.of([record], device)
    view = torch.zeros(table.count, dtype=torch.long, device=device)
    colour = None if color is None else color.to(device)
    if record.optics is not None:
        looks, tracks = field_looks(table, torch.arange(table.count, device=device), rows, views,
                                    view, table.start, beta=float(beta), dtype=dtype, color=colour)
        return (looks, tracks, None) if kept else (looks, tracks)
    h0 = homogeneous(views.project[view], table.start)
    keep = torch.nonzero(h0.detach()[:, 2] > NEAR).squeeze(1)
    looks = fixed_looks(table.select(keep), rows, resolution)
    colour = table.color if colour is None else colour
    n = keep.numel()
    tracks = Tracks(entry=torch.arange(n, device=device), view=view[keep], h0=h0[keep],
                    hd=direction(views.project[view[keep]], table.displacement[keep]),
                    samples=rows.samples[table.record[keep]],
                    spacing=rows.spacing[table.record[keep]],
                    theta=table.transparency[keep].to(dtype), color=colour[keep].to(dtype),
                    beta=torch.full((n,), float(beta), dtype=torch.float64, device=device))
    return (looks, tracks, keep) if kept else (looks, tracks)


def empty_looks(device) -> Looks:
    z = torch.zeros(0, dtype=torch.float64, device=device)
    i = torch.zeros(0, dtype=torch.long, device=device)
    return Looks(footprint=z, defocus=i, rotation=z, template=i,
                 brighten=torch.zeros(0, dtype=torch.bool, device=device))


def empty_tracks(device, dtype) -> Tracks:
    i = torch.zeros(0, dtype=torch.long, device=device)
    h = torch.zeros(0, 3, dtype=torch.float64, device=device)
    return Tracks(entry=i, view=i, h0=h, hd=h, samples=i,
                  spacing=torch.zeros(0, dtype=torch.float64, device=device),
                  theta=torch.zeros(0, dtype=dtype, device=device),
                  color=torch.zeros(0, 3, dtype=dtype, device=device),
                  beta=torch.zeros(0, dtype=torch.float64, device=device))


# -- blur samples ----------------------------------------------------------------------------

@dataclass
class Instances:
    """I blur samples, projected: the splat's input.

    Shape: u, v, z (I,) in the images' dtype (pixel position and camera depth, differentiable);
    theta (I,) θ / K; color (I, 3); beta (I,) float64; entry, view (I,) int64.
    """

    u: torch.Tensor
    v: torch.Tensor
    z: torch.Tensor
    theta: torch.Tensor
    color: torch.Tensor
    beta: torch.Tensor
    entry: torch.Tensor
    view: torch.Tensor

    @property
    def count(self) -> int:
        return int(self.entry.numel())


#: Most blur samples of one track and view: a streak whose length (see :func:`streak_samples`)
#: exceeds ``MAX_BLUR_SAMPLES − 1`` pixels gets gaps of ``L / (MAX_BLUR_SAMPLES − 1)`` pixels.
MAX_BLUR_SAMPLES = 256


def streak_samples(tracks: Tracks, gap: Optional[torch.Tensor] = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """The number of blur samples of every track and their spacing, adapted to the streak's
    length in pixels so that consecutive samples lie at most ``g`` pixels apart:
    ``K_t = clamp(ceil(L_t / g) + 1, K, MAX_BLUR_SAMPLES)`` samples spread over the same streak
    (``spacing_t = (K − 1) spacing / (K_t − 1)``), K the record's ``blur_samples``.

    ``gap``: g per stamp entry (the :class:`~weathergen.engine.rendering.stamps.StampSet`'s ``gap``, read
    at each track's entry): a stamp that is smooth over several pixels (softened) leaves no
    ripple between samples that far apart; None: one pixel for every track.

    ``L_t`` is the streak's length in pixels measured at the slope of its nearer end: the
    streak ``p(s) = (a + s b) / (c + s e)`` (``h0 = (a, c)``, ``hd = (b, e)``) has
    ``|dp/ds| = |b c − a e| / z(s)²``, largest where the depth z is smallest, so
    ``L_t = s_max |b c − a e| / z_min²`` bounds every gap by ``L_t / (K_t − 1)`` (it is the
    projected length when the depth does not change, ``z_far / z_near`` times it otherwise).
    Tracks without blur (K = 1) and short streaks (``L_t <= K − 1``) keep K and their spacing
    bit for bit. Shape: T tracks -> (samples (T,) int64, spacing (T,) float64)."""
    k = tracks.samples
    if tracks.count == 0 or bool((k <= 1).all()):
        return k, tracks.spacing
    with torch.no_grad():
        reach = (k - 1) * tracks.spacing                                  # s_max
        h0, hd = tracks.h0, tracks.hd
        # the first two components of h0 x hd are (−(b_v c − a_v e), b_u c − a_u e)
        cross = torch.linalg.cross(h0, hd)[:, :2]
        z0 = h0[:, 2]
        near = torch.minimum(z0, torch.addcmul(z0, reach, hd[:, 2])).clamp_(min=NEAR)
        length = reach * torch.sqrt((cross * cross).sum(1)) / (near * near)
        length = torch.nan_to_num(length, nan=0.0)
        if gap is not None:
            length = length / gap.index_select(0, tracks.entry)
        length = length.clamp_(max=MAX_BLUR_SAMPLES - 1)
        samples = torch.maximum(torch.ceil(length).long() + 1, k)
        spacing = torch.where(samples == k, tracks.spacing, reach / (samples - 1))
    return samples, spacing


def blur_samples(tracks: Tracks, dtype: torch.dtype, gap: Optional[torch.Tensor] = None
                 ) -> Instances:
    """Every track's K_t blur samples at ``h0 + k · spacing_t · hd`` (k = 0 .. K_t − 1,
    :func:`streak_samples`), projected, each with θ / K_t.
    Shape: T tracks -> I = Σ K_t instances, a track's samples consecutive."""
    device = tracks.h0.device
    samples, spacing = streak_samples(tracks, gap)
    tracks = Tracks(entry=tracks.entry, view=tracks.view, h0=tracks.h0, hd=tracks.hd,
                    samples=samples, spacing=spacing, theta=tracks.theta, color=tracks.color,
                    beta=tracks.beta)
    total = int(tracks.samples.sum()) if tracks.count else 0
    track = torch.repeat_interleave(tracks.samples, output_size=total)
    first = torch.cumsum(tracks.samples, 0) - tracks.samples
    k = torch.arange(total, device=device) - first.index_select(0, track)
    step = (k * tracks.spacing.index_select(0, track))[:, None]
    h = tracks.h0.index_select(0, track) + step * tracks.hd.index_select(0, track)
    z = h[:, 2]
    safe = torch.where(z.abs() > 1e-12, z, scalar(1e-12, z.device))
    per_sample = tracks.theta / tracks.samples.to(tracks.theta.dtype)
    entry, view = torch.stack((tracks.entry, tracks.view)).index_select(1, track)
    return Instances(u=(h[:, 0] / safe).to(dtype), v=(h[:, 1] / safe).to(dtype), z=z.to(dtype),
                     theta=per_sample.index_select(0, track),
                     color=tracks.color.index_select(0, track),
                     beta=tracks.beta.index_select(0, track), entry=entry, view=view)
