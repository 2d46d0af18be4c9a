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

import itertools
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
import torch.nn.functional as F

from .optics import FieldOptics
from .particles import Particles
from .sampling import NEAR

#: Largest thin-lens defocus radius of a field particle, pixels.
MAX_DEFOCUS = 20


# -- one camera ------------------------------------------------------------------------------

@dataclass
class View:
    """One camera looking at the particles.

    Shape: intrinsics (3, 3), cam_from_ref (4, 4), depth (1, H, W) camera-z of the scene.
    """

    intrinsics: torch.Tensor
    cam_from_ref: torch.Tensor
    depth: torch.Tensor

    @property
    def size(self) -> tuple[int, int]:
        return int(self.depth.shape[-2]), int(self.depth.shape[-1])


@dataclass
class Views:
    """The V cameras of one render call, all of one image size.

    Shape: project (V, 3, 4) float64, ``K [R | t]`` (reference frame -> homogeneous pixels);
    focal (V,) float64, ``sqrt(fx fy)``; depth (V, 1, H, W), the scene's camera-z (no gradient).
    """

    project: torch.Tensor
    focal: torch.Tensor
    depth: torch.Tensor

    @classmethod
    def of(cls, intrinsics: torch.Tensor, cam_from_ref: torch.Tensor, depth: torch.Tensor,
           device=None) -> "Views":
        """Shape: intrinsics (V, 3, 3), cam_from_ref (V, 4, 4), depth (V, 1, H, W)."""
        device = depth.device if device is None else device
        k = intrinsics.to(device=device, dtype=torch.float64)
        cam = cam_from_ref.to(device=device, dtype=torch.float64)[:, :3, :]
        # K's columns (V, 3, 1) times the camera's rows (V, 1, 4)
        (k0, k1, k2), (c0, c1, c2) = k.unsqueeze(3).unbind(2), cam.unsqueeze(1).unbind(2)
        project = k0 * c0 + k1 * c1 + k2 * c2
        # (fx fy: the product of the diagonal's first two)
        return cls(project=project, focal=torch.sqrt(k.diagonal(dim1=1, dim2=2)[:, :2].prod(1)),
                   depth=(depth.detach() if depth.requires_grad else depth).to(device))

    @property
    def count(self) -> int:
        return int(self.project.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        return int(self.depth.shape[-2]), int(self.depth.shape[-1])


def homogeneous(project: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """``K [R | t] [X; 1]`` row by row: (u z, v z, z), each a sum over the three coordinates
    (an innermost reduction: the same bits whatever the number of rows, unlike a batched matrix
    product). Shape: (N, 3, 4), (..., N, 3) -> (..., N, 3)."""
    return (project[:, :, :3] * points[..., None, :]).sum(-1) + project[:, :, 3]


def direction(project: torch.Tensor, vectors: torch.Tensor) -> torch.Tensor:
    """``K R d`` row by row. Shape: (N, 3, 4), (N, 3) -> (N, 3)."""
    return (project[:, :, :3] * vectors[:, None, :]).sum(-1)


# -- the weather-field model's looks ----------------------------------------------------------

def focal(intrinsics: torch.Tensor) -> float:
    """``sqrt(fx fy)``: pixels per scene unit at unit depth."""
    k = intrinsics.double()
    return float(torch.sqrt(k[0, 0] * k[1, 1]))


def footprint(f, diameter: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """Particle diameter on screen in pixels. Shape: (N,), (N,) -> (N,)."""
    return f * diameter / z


def _smoothstep(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(0, 1)
    return x * x * (3 - 2 * x)


_SCALARS: dict = {}


def _scalar(value: float, device) -> torch.Tensor:
    """A 0-dim float64 tensor holding ``value``, made once per device (``torch.where`` with a
    Python number makes one at every call: an operation each time). It broadcasts and promotes
    as the number does."""
    key = (value, str(device))
    if key not in _SCALARS:
        _SCALARS[key] = torch.tensor(value, dtype=torch.float64, device=device)
    return _SCALARS[key]


def coc_radius(f, aperture, focus, z: torch.Tensor) -> torch.Tensor:
    """Thin-lens circle of confusion ``round(clip(f A |1/z − 1/focus| / 2, 0, MAX_DEFOCUS))``
    in whole pixels (0 where the aperture is 0). Arguments broadcast. Shape: -> z's, int64."""
    r = 0.5 * f * aperture * (torch.reciprocal(z) - _inverse(focus)).abs()
    r = torch.floor(r.clamp(0, MAX_DEFOCUS) + 0.5)
    return torch.where(torch.as_tensor(aperture, device=z.device) > 0, r,
                       _scalar(0.0, z.device)).long()


def defocus_radius(f: float, optics: FieldOptics, z: torch.Tensor) -> torch.Tensor:
    """Circle-of-confusion radius in whole pixels. Shape: (N,) -> (N,) int64."""
    return coc_radius(f, optics.aperture, optics.focus, z)


def fade(near, far, fraction, z: torch.Tensor) -> torch.Tensor:
    """Fade-in over ``[near, 2 near]``, fade-out over the last ``fraction`` of ``far`` (a cut at
    ``far`` where the fraction is 0). Arguments broadcast. Shape: -> z's."""
    fade_in = _smoothstep((z - near) / near)
    fraction = torch.as_tensor(fraction, dtype=z.dtype, device=z.device)
    cut = fraction > 0
    safe = torch.where(cut, fraction, _scalar(1.0, z.device))
    fade_out = torch.where(cut, _smoothstep((far - z) / (safe * far)),
                           (z <= far).to(z.dtype))
    return fade_in * fade_out


def depth_fade(optics: FieldOptics, z: torch.Tensor) -> torch.Tensor:
    """Fade-in after ``near`` and fade-out before ``far``, in [0, 1]. Shape: any -> same."""
    return fade(optics.near, optics.far, optics.fade, z)


def in_view(ends: torch.Tensor, reach: torch.Tensor, tolerance: torch.Tensor,
            depth: torch.Tensor, view: torch.Tensor,
            windows: Optional[DepthWindows] = None) -> torch.Tensor:
    """Whether a streak's start or end lands in its view's image widened by ``reach`` pixels and
    not behind the scene by more than ``tolerance`` everywhere its stamp reaches: the test reads
    the farthest scene depth over the image pixels within ``reach`` of the point (a cloud whose
    centre lies behind a wall but whose stamp reaches past the wall's edge is drawn), taken from
    :func:`depth_windows`' blocks (possibly a little more than the window: never less).

    Shape: ends (2, M, 3) float64 homogeneous pixels of the start and the end, reach (M,),
    tolerance (M,) or a number, depth (V, 1, H, W), view (M,) int64 -> (M,) bool.
    ``windows``: :func:`depth_windows` of ``depth``, from a caller that tests many points
    against the same views (the sampler): each point is then tested at its own pixel first and
    only those behind the scene there over their window (the same result, as the window holds the
    pixel, in less time; one host synchronisation).
    """
    height, width = depth.shape[-2:]
    zz = ends[..., 2]
    safe = torch.where(zz.abs() > 1e-12, zz, _scalar(1e-12, zz.device))
    uv = ends[..., :2] / safe[..., None]                                # (2, M, 2): u, v
    reach = reach[:, None]
    limit, last, step = _image_constants(height, width, ends.device)
    reaches = (zz > 1e-6) & ((uv >= -0.5 - reach) & (uv <= limit + reach)).all(-1)
    if windows is None:     # a render's points: every window at once
        window = _window(uv, reach, last)
        level = window_level(window)
        # (the pyramid up to the widest window's level: one host synchronisation)
        top = int(level.max()) if level.numel() else 0
        under = depth_windows(depth, top).farthest(window, view, level)
        return (reaches & (zz <= under.to(torch.float64) + tolerance)).any(0)
    # the sampler's many candidates: the point's own pixel first (most points in empty space
    # pass there; the window holds it, so a point that passes there passes the window's test)
    pixel = torch.minimum(torch.floor(uv + 0.5).clamp_(min=0), last).long()   # (col, row)
    under = torch.take(depth, (pixel * step).sum(-1) + view * (height * width))
    seen = reaches & (zz <= under.to(torch.float64) + tolerance)
    # the others: the farthest depth over the window of pixels within ``reach``
    rest = torch.nonzero((reaches & ~seen).view(-1)).squeeze(1)
    if rest.numel():
        m = torch.remainder(rest, zz.shape[1])
        r = reach.view(-1).index_select(0, m)[:, None]
        point = uv.reshape(-1, 2).index_select(0, rest)
        farthest = windows.farthest(_window(point, r, last), view.index_select(0, m))
        if torch.is_tensor(tolerance) and tolerance.dim():
            tolerance = tolerance.index_select(0, m)
        behind = zz.reshape(-1).index_select(0, rest) <= farthest.to(torch.float64) + tolerance
        seen = seen.reshape(-1).index_copy(0, rest, behind).view(seen.shape)
    return seen.any(0)


def _window(uv: torch.Tensor, reach: torch.Tensor, last: torch.Tensor) -> torch.Tensor:
    """The first and last image pixels (column, row) within ``reach`` of points ``uv``, clamped
    to the image (``last``: its last column and row). Shape: uv (..., 2), reach broadcasting
    to it -> (2, ..., 2) int64."""
    return torch.minimum(torch.stack((uv - reach, uv + reach)).add_(0.5).floor_().clamp_(min=0),
                         last).long()


@dataclass
class DepthWindows:
    """A view's scene depth and its maxima over ``2**k x 2**k`` blocks (k = 0, 1, ... up to one
    block for the whole image), every level flat in ``values``; per level k, ``table[k]`` =
    (where it starts, h_k w_k, w_k): level k is ``(V, h_k, w_k)``, ``h_k = ceil(H / 2**k)``."""

    values: torch.Tensor
    table: torch.Tensor

    def farthest(self, window: torch.Tensor, view: torch.Tensor,
                 level: Optional[torch.Tensor] = None) -> torch.Tensor:
        """The largest depth over the blocks of the smallest level whose blocks are as wide as
        the window (at most two per axis hold it). Shape: window (2, ..., M, 2) int64, its first
        and last pixels (col, row); view (M,) -> (..., M). ``level``: :func:`window_level` of
        ``window`` when the caller has it (it is then clamped in place)."""
        k = (window_level(window) if level is None else level).clamp_(
            max=self.table.shape[0] - 1)
        start, size, w = self.table.index_select(0, k.view(-1)).view(*k.shape, 3).unbind(-1)
        col, row = (window >> k[..., None]).unbind(-1)                     # (2, ..., M)
        at = torch.addcmul(torch.addcmul(start, view, size), row, w)[:, None] + col  # (2, 2, ..., M)
        return self.values.take(at).amax((0, 1))


def window_level(window: torch.Tensor) -> torch.Tensor:
    """The :class:`DepthWindows` level that holds each window in at most two blocks per axis:
    ``2**k >= n`` for its side n, k the binary exponent of ``n − 1``. Shape: window
    (2, ..., M, 2) -> (..., M) int32."""
    return torch.frexp((window[1] - window[0]).amax(-1).to(torch.float64))[1]


_TABLES: dict = {}


def depth_windows(depth: torch.Tensor, top: Optional[int] = None) -> DepthWindows:
    """:class:`DepthWindows` of ``depth`` (V, 1, H, W): block maxima by repeated 2 x 2 max
    pooling (a block at the image's right or bottom edge holds what lies inside), up to level
    ``top`` (None: up to one block for the whole image)."""
    levels = [depth]
    while (levels[-1].shape[-1] > 1 or levels[-1].shape[-2] > 1) \
            and (top is None or len(levels) <= top):
        levels.append(F.max_pool2d(levels[-1], 2, ceil_mode=True))
    key = (tuple(tuple(lv.shape) for lv in levels), str(depth.device))
    if key not in _TABLES:
        starts = itertools.accumulate([lv.numel() for lv in levels[:-1]], initial=0)
        if len(_TABLES) > 64:
            _TABLES.clear()
        _TABLES[key] = torch.tensor([[s, lv.shape[-2] * lv.shape[-1], lv.shape[-1]]
                                     for s, lv in zip(starts, levels)], device=depth.device)
    return DepthWindows(values=torch.cat([lv.reshape(-1) for lv in levels]), table=_TABLES[key])


_IMAGE: dict = {}


def _image_constants(height: int, width: int, device) -> tuple:
    """Per axis (u, v) of an image: its edges' centres plus half a pixel ``(W − 0.5, H − 0.5)``
    and its last pixels ``(W − 1, H − 1)`` (float64), and a pixel's index steps ``(1, W)``
    (each made once per size and device)."""
    key = (height, width, str(device))
    if key not in _IMAGE:
        _IMAGE[key] = (torch.tensor([width - 0.5, height - 0.5], dtype=torch.float64,
                                    device=device),
                       torch.tensor([width - 1.0, height - 1.0], dtype=torch.float64,
                                    device=device),
                       torch.tensor([1, width], device=device))
    return _IMAGE[key]


def _fixed(x: torch.Tensor) -> torch.Tensor:
    """``x.detach()`` where ``x`` carries a gradient, ``x`` itself otherwise (the same numbers
    without an operation)."""
    return x.detach() if x.requires_grad else x


def _inverse(x):
    """``1 / x`` of a tensor (one reciprocal: ``1.0 / x`` is a reciprocal and a product) or of a
    number."""
    return torch.reciprocal(x) if torch.is_tensor(x) else 1.0 / x


@dataclass
class OpticsRows:
    """Field optics per row (a broadcastable stand-in for :class:`FieldOptics`). Shape: (M,)
    float64 each."""

    near: torch.Tensor
    far: torch.Tensor
    fade: torch.Tensor
    aperture: torch.Tensor
    focus: torch.Tensor
    depth_softness: torch.Tensor


def field_mask(project: torch.Tensor, f: torch.Tensor, start: torch.Tensor,
               streak: torch.Tensor, diameter: torch.Tensor, optics, depth: torch.Tensor,
               view: torch.Tensor, windows: Optional[DepthWindows] = None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Which field particles a view draws, their camera depth there and their defocus radius:
    camera depth in ``[near, far]``, start or streak end inside the image widened by the
    stamp's reach (half the footprint, the defocus radius and 2 pixels), not behind the scene by
    more than three ``depth_softness`` everywhere within that reach (:func:`in_view`).

    Shape: project (M, 3, 4), f (M,), start, streak (M, 3), diameter (M,) float64; ``optics`` a
    :class:`FieldOptics` or :class:`OpticsRows`; depth (V, 1, H, W); view (M,) int64 ->
    ``(mask (M,) bool, z (M,) float64, radius (M,) int64)`` (z and radius where drawn, those
    at ``far`` elsewhere). ``windows``: :func:`depth_windows` of ``depth``, when the caller
    tests many particles against the same views.
    """
    mask, z, radius, _, _ = _field_mask(project, f, start, streak, diameter, optics, depth,
                                        view, windows)
    return mask, z, radius


def _field_mask(project, f, start, streak, diameter, optics, depth, view, windows=None):
    """:func:`field_mask`, the footprint ``f d / z`` there and the homogeneous pixels of the
    start, differentiable in ``start`` (the mask and the depth are not).
    Shape: -> (mask, z, radius, footprint (M,), h0 (M, 3))."""
    # (detached only where a gradient flows: a detach is an operation)
    ends = homogeneous(project, torch.stack((start, _fixed(start) + streak)))
    fixed = _fixed(ends)
    z = fixed[0, :, 2]
    in_range = (z >= optics.near) & (z <= optics.far)
    safe = torch.where(in_range, z, optics.far)
    radius = coc_radius(f, optics.aperture, optics.focus, safe)
    size = footprint(f, diameter, safe)
    reach = 0.5 * size + radius + 2
    seen = in_view(fixed, reach, 3 * optics.depth_softness, depth, view, windows)
    return in_range & seen, safe, radius, size, ends[0]


def view_mask(view: View, points: torch.Tensor, streak: torch.Tensor, diameter: torch.Tensor,
              optics: FieldOptics, windows: Optional[DepthWindows] = None) -> torch.Tensor:
    """Which particles a view draws (see :func:`field_mask`; the render core applies the same
    test to every view it draws).

    Shape: points (M, 3) reference coordinates, streak (M, 3) the streak's end minus its start,
    diameter (M,) -> (M,) bool. Computed in float64 on the device of the view's depth (the
    CPU for a view made from CPU tensors). ``windows``: the view's :func:`view_windows`, when
    many calls test the same view.
    """
    dev = view.depth.device
    views = Views.of(view.intrinsics[None], view.cam_from_ref[None], view.depth[None],
                     device=dev)
    m = points.shape[0]
    index = torch.zeros(m, dtype=torch.long, device=dev)
    mask, _, _ = field_mask(views.project.expand(m, 3, 4), views.focal.expand(m),
                            points.double().to(dev), streak.double().to(dev),
                            diameter.double().to(dev), optics, views.depth, index, windows)
    return mask


def view_windows(view: View) -> DepthWindows:
    """The :class:`DepthWindows` :func:`view_mask` reads for ``view`` (build them once for many
    calls on one view), on the device of its depth."""
    return depth_windows(view.depth[None].detach())


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
    drawn on a coarser grid); research (R,) bool (stamps made as the research code makes them).
    """

    samples: torch.Tensor
    spacing: torch.Tensor
    blur_length: torch.Tensor
    brighten: torch.Tensor
    optics: torch.Tensor
    coarse: torch.Tensor
    research: torch.Tensor

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
                   research=torch.tensor(research, dtype=torch.bool, device=device))


def fixed_looks(table: ParticleTable, rows: RecordRows, resolution: int) -> Looks:
    """The paper's model: looks fixed at sampling (footprint ``scale`` x template pixels; for a
    ``research`` record the disc of the area of the ``n x n`` window, n = floor(footprint),
    into which the research code resamples its flakes, :data:`RESEARCH_DISC` n, at most the
    footprint itself)."""
    research = rows.research[table.record]
    footprint = table.scale * resolution
    window = torch.minimum(footprint.floor() * RESEARCH_DISC, footprint)
    footprint = torch.where(research, window, footprint).clamp(min=1.0)
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
    streak = length[:, None] * _fixed(displacement)
    mask, z, radius, fp, h0 = _field_mask(project, f, start, streak, scale,
                                          OpticsRows(near, far, fraction, aperture, focus,
                                                     softness), views.depth, view)
    factor = fade(near, far, fraction, z) * fp.clamp(max=1.0) ** 2
    theta = (table.transparency.index_select(0, which).to(torch.float64) * factor).to(dtype)
    keep = torch.nonzero(mask & (_fixed(theta) != 0)).squeeze(1)
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

    ``gap``: g per stamp entry (the :class:`~weathergen.engine.stamps.StampSet`'s ``gap``, read
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
    safe = torch.where(z.abs() > 1e-12, z, _scalar(1e-12, z.device))
    per_sample = tracks.theta / tracks.samples.to(tracks.theta.dtype)
    entry, view = torch.stack((tracks.entry, tracks.view)).index_select(1, track)
    return Instances(u=(h[:, 0] / safe).to(dtype), v=(h[:, 1] / safe).to(dtype), z=z.to(dtype),
                     theta=per_sample.index_select(0, track),
                     color=tracks.color.index_select(0, track),
                     beta=tracks.beta.index_select(0, track), entry=entry, view=view)
