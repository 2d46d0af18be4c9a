"""A second camera of a stereo rig looking at the same particles.

A field record (or the paper's) is data in a reference frame, so a second camera only needs its
own transform from that frame, ``cam_right_from_ref = right_from_left @ cam_left_from_ref``, and
its own scene depth for the occlusion test. Datasets rarely ship the right view's depth; it is
forward-warped from the left one (:func:`warp_view_depth`): each left pixel is back-projected,
moved into the right camera and z-buffered into the four pixels around where it lands. Pixels
that no left pixel reaches (disoccluded, or beyond the left view) take the depth of the
background side along their row, the farther of the nearest reached pixels to their left and
right (the standard hole filling of view synthesis: what a near object uncovers lies behind it),
never the far depth of the sky unless that side is sky. The depth provenance is carried along (a
hole filled this way is ``COMPLETED``). For a rectified pair the particles land at disparity
``f · B / z`` (tested).
"""

from __future__ import annotations

import math
from typing import Optional

import torch

from ...framepair import COMPLETED, MEASURED, UNKNOWN
from ...geometry import backproject, project, transform_points
from .combined import render_layers_view
from ..records.layered import LayeredParticles
from ..records.particles import Particles
from .renderer import BETA_RENDER, render_view
from ..views import View


def warp_view_depth(depth: torch.Tensor, provenance: Optional[torch.Tensor],
                    intrinsics: torch.Tensor, right_from_left: torch.Tensor,
                    right_intrinsics: Optional[torch.Tensor] = None,
                    fill: Optional[float] = None) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    """The right camera's depth and its provenance (each right pixel the class of the left pixel
    it shows; a filled hole ``COMPLETED``, or ``SKY`` if its background is sky). ``provenance``
    None gives None.

    Shape: depth (1, H, W), provenance (1, H, W) uint8 or None -> ((1, H, W), (1, H, W) or None).
    """
    h, w = depth.shape[-2:]
    k_right = intrinsics if right_intrinsics is None else right_intrinsics
    pts = backproject(depth.double(), intrinsics.double()).reshape(3, -1).T      # (HW, 3)
    pix, z = project(transform_points(right_from_left.double(), pts), k_right.double())
    out = torch.full((h * w,), math.inf, dtype=torch.float64, device=depth.device)
    # each left pixel covers the four right pixels around where it lands (no cracks between
    # neighbours at fractional shifts); the z-buffer keeps the nearest surface
    c0, r0 = torch.floor(pix[:, 0]).long(), torch.floor(pix[:, 1]).long()
    hits = []
    for dc in (0, 1):
        for dr in (0, 1):
            col, row = c0 + dc, r0 + dr
            ok = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            hits.append((row[ok] * w + col[ok], z[ok], ok))
            out = out.scatter_reduce(0, hits[-1][0], hits[-1][1], reduce="amin", include_self=True)
    kind = None if provenance is None else _winners(out, hits, provenance.reshape(-1).to(out.device))
    reached = torch.isfinite(out).view(h, w)
    if fill is not None:
        out = torch.where(reached.reshape(-1), out, torch.full_like(out, float(fill)))
        kind = None if kind is None else torch.where(reached.reshape(-1), kind,
                                                     torch.full_like(kind, UNKNOWN))
        return _shaped(out, kind, depth, h, w)
    far = float(depth.max())
    out, kind = _background_fill(out.view(h, w), reached, kind, far)
    return _shaped(out, kind, depth, h, w)


def _shaped(out, kind, depth, h, w):
    return (out.reshape(1, h, w).to(depth.dtype),
            None if kind is None else kind.reshape(1, h, w).to(torch.uint8))


def _winners(out, hits, provenance):
    """The provenance of the left pixel each right pixel shows (the z-buffer's winner; the lowest
    class among equal depths). Shape: -> (H W,) int64, UNKNOWN where nothing landed."""
    kind = torch.full_like(out, UNKNOWN, dtype=torch.int64)
    for index, z, ok in hits:
        won = z == out[index]
        kind = kind.scatter_reduce(0, index[won], provenance[ok][won].long(), reduce="amin",
                                   include_self=True)
    return kind


def _background_fill(depth, reached, kind, far: float):
    """Holes take the farther of the nearest reached pixels on their left and right in their row
    (the one side where the other has none); a row without any takes ``far``. The class of a
    filled hole is its source's, ``COMPLETED`` for a measured one.

    Shape: depth (H, W) float64 (holes any value), reached (H, W) bool, kind (H W,) or None.
    """
    h, w = depth.shape
    cols = torch.arange(w, device=depth.device).expand(h, w)
    left = torch.cummax(torch.where(reached, cols, -1), dim=1).values
    right = torch.cummin(torch.where(reached, cols, w).flip(1), dim=1).values.flip(1)
    left_z = depth.gather(1, left.clamp(min=0))
    right_z = depth.gather(1, right.clamp(max=w - 1))
    take_right = (right < w) & ((left < 0) | (right_z > left_z))
    source = torch.where(take_right, right, left)
    some = source >= 0
    filled = torch.where(some, depth.gather(1, source.clamp(min=0)), torch.full_like(depth, far))
    out = torch.where(reached, depth, filled).reshape(-1)
    if kind is None:
        return out, None
    kind2 = kind.view(h, w)
    from_side = kind2.gather(1, source.clamp(min=0))
    from_side = torch.where(from_side == MEASURED, COMPLETED, from_side)
    hole_kind = torch.where(some, from_side, torch.full_like(from_side, UNKNOWN))
    return out, torch.where(reached, kind2, hole_kind).reshape(-1)


def stereo_view(left: View, right_from_left: torch.Tensor, right_depth: torch.Tensor,
                right_intrinsics: Optional[torch.Tensor] = None) -> View:
    """The right camera as a :class:`View` of the same reference frame."""
    k = left.intrinsics if right_intrinsics is None else right_intrinsics
    return View(k, right_from_left.double() @ left.cam_from_ref.double(), right_depth)


def render_right(image: torch.Tensor, right: View, particles: Particles, start: torch.Tensor,
                 displacement: torch.Tensor, templates, *, beta: float = BETA_RENDER,
                 chunk_elements: Optional[int] = None, frame: int = 0):
    """The weather frame of the right camera: the same particles, its own looks per frame, and
    the record's atmosphere as in frame ``frame`` (0 or 1) of the pair (the same density at
    the same world point as the left camera's).

    Shape: image (3, H, W) -> (image (3, H, W), opacity (1, H, W)).
    """
    return render_view(image, right, particles, start, displacement, templates, beta=beta,
                       chunk_elements=chunk_elements, frame=frame)


def render_right_layers(images, views, particles: LayeredParticles, *,
                        beta: float = BETA_RENDER) -> tuple[list, list]:
    """The weather frames of the right camera for combined weather: each frame's layers drawn
    from its view alone (:func:`stereo_view` of the frame; frame ``t`` from the particles'
    positions in frame ``t``), depth-ordered as :func:`~weathergen.engine.render_layers` does,
    as :func:`render_right` draws a single record.

    Shape: images one or two (3, H, W), views as many :class:`View` -> (as many images
    (3, H, W), as many opacities (1, H, W)).
    """
    frames, opacities = [], []
    for t, (image, view) in enumerate(zip(images, views)):
        out, opacity = render_layers_view(image, view, particles, frame=t, beta=beta)
        frames.append(out)
        opacities.append(opacity)
    return frames, opacities
