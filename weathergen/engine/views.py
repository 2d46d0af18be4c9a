"""One camera and what it sees of a weather field: :class:`View`, :class:`Views` (a render
call's cameras as projection rows), a field particle's looks in a view (footprint, thin-lens
defocus, depth fade) and the view mask (:func:`field_mask`), with which the field model samples
and the render core draws. Products are elementwise with sums over the last axis (no matrix
products), so that a particle's numbers do not depend on how many others the call holds."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F

from .weather.optics import FieldOptics

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


def scalar(value: float, device) -> torch.Tensor:
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
    # one reciprocal for a tensor focus (``1.0 / x`` is a reciprocal and a product)
    inverse_focus = torch.reciprocal(focus) if torch.is_tensor(focus) else 1.0 / focus
    r = 0.5 * f * aperture * (torch.reciprocal(z) - inverse_focus).abs()
    r = torch.floor(r.clamp(0, MAX_DEFOCUS) + 0.5)
    return torch.where(torch.as_tensor(aperture, device=z.device) > 0, r,
                       scalar(0.0, z.device)).long()


def fade(near, far, fraction, z: torch.Tensor) -> torch.Tensor:
    """Fade-in over ``[near, 2 near]``, fade-out over the last ``fraction`` of ``far`` (a cut at
    ``far`` where the fraction is 0). Arguments broadcast. Shape: -> z's."""
    fade_in = _smoothstep((z - near) / near)
    fraction = torch.as_tensor(fraction, dtype=z.dtype, device=z.device)
    cut = fraction > 0
    safe = torch.where(cut, fraction, scalar(1.0, z.device))
    fade_out = torch.where(cut, _smoothstep((far - z) / (safe * far)),
                           (z <= far).to(z.dtype))
    return fade_in * fade_out


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
    safe = torch.where(zz.abs() > 1e-12, zz, scalar(1e-12, zz.device))
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


def detached(x: torch.Tensor) -> torch.Tensor:
    """``x.detach()`` where ``x`` carries a gradient, ``x`` itself otherwise (the same numbers
    without an operation)."""
    return x.detach() if x.requires_grad else x


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
    mask, z, radius, _, _ = field_mask_looks(project, f, start, streak, diameter, optics, depth,
                                        view, windows)
    return mask, z, radius


def field_mask_looks(project, f, start, streak, diameter, optics, depth, view, windows=None):
    """:func:`field_mask`, the footprint ``f d / z`` there and the homogeneous pixels of the
    start, differentiable in ``start`` (the mask and the depth are not).
    Shape: -> (mask, z, radius, footprint (M,), h0 (M, 3))."""
    # (detached only where a gradient flows: a detach is an operation)
    ends = homogeneous(project, torch.stack((start, detached(start) + streak)))
    fixed = detached(ends)
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
