"""A second camera of a stereo rig looking at the same particles.

A field record (or the paper's) is data in a reference frame, so a second camera only needs its
own transform from that frame, ``cam_right_from_ref = right_from_left @ cam_left_from_ref``, and
its own scene depth for the occlusion test. Datasets rarely ship the right view's depth; it is
forward-warped from the left one (:func:`warp_depth`): each left pixel is back-projected, moved into
the right camera and z-buffered into the four pixels around where it lands, and pixels that no
left pixel reaches (disoccluded, or beyond the left view) get ``fill`` (by default the farthest
left depth), so particles in front of them stay visible. For a rectified pair the particles land
at disparity ``f · B / z`` (tested).
"""

from __future__ import annotations

from typing import Optional

import torch

from ...geometry import backproject, project, transform_points
from .combined import render_layers_view
from ..records.layered import LayeredParticles
from ..records.particles import Particles
from .renderer import BETA_RENDER, render_view
from .tracks import View


def warp_depth(depth: torch.Tensor, intrinsics: torch.Tensor, right_from_left: torch.Tensor,
               right_intrinsics: Optional[torch.Tensor] = None,
               fill: Optional[float] = None) -> torch.Tensor:
    """The right camera's depth, forward-warped from the left camera's with a z-buffer.

    Shape: depth (1, H, W), intrinsics (3, 3), right_from_left (4, 4) -> (1, H, W), same dtype.
    """
    h, w = depth.shape[-2:]
    k_right = intrinsics if right_intrinsics is None else right_intrinsics
    pts = backproject(depth.double(), intrinsics.double()).reshape(3, -1).T      # (HW, 3)
    pix, z = project(transform_points(right_from_left.double(), pts), k_right.double())
    far = float(depth.max()) if fill is None else float(fill)
    out = torch.full((h * w,), far, dtype=torch.float64)
    # each left pixel covers the four right pixels around where it lands (no cracks between
    # neighbours at fractional shifts); the z-buffer keeps the nearest surface
    c0, r0 = torch.floor(pix[:, 0]).long(), torch.floor(pix[:, 1]).long()
    for dc in (0, 1):
        for dr in (0, 1):
            col, row = c0 + dc, r0 + dr
            ok = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
            out = out.scatter_reduce(0, row[ok] * w + col[ok], z[ok], reduce="amin",
                                     include_self=True)
    return out.view(1, h, w).to(depth.dtype)


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
