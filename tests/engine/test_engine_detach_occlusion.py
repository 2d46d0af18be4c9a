"""``detach_occlusion``: the visibility V passes no gradient to the particle depth, while the
forward pass and every other gradient stay as they are.

Particles sit just in front of a wall (V between 0 and 1 at β = 30) and move along their own
camera rays: that changes their depth and nothing else (the cameras coincide and nothing moves),
so the whole gradient along the rays is V's. Both render paths are checked: the paper's records
and weather-field records (the per-frame path)."""

from __future__ import annotations

import pytest
import torch

from weathergen.engine import FieldOptics, Particles, RenderSettings, TemplateLibrary, render
from weathergen.framepair import FramePair, PairId

H, W, F = 32, 40, 40.0
WALL = 4.0


def disc_library(res: int = 12) -> TemplateLibrary:
    c = (res - 1) / 2
    yy, xx = torch.meshgrid(torch.arange(res, dtype=torch.float64),
                            torch.arange(res, dtype=torch.float64), indexing="ij")
    disc = (((xx - c) ** 2 + (yy - c) ** 2) <= (res / 2) ** 2).float()
    return TemplateLibrary(name="test-disc", alphas=disc[None], digest="")


def record(field: bool) -> Particles:
    position = torch.tensor([[0.3, -0.2, WALL - 0.02], [-0.5, 0.4, WALL + 0.01],
                             [0.1, 0.5, WALL - 0.05]], dtype=torch.float64)
    n = position.shape[0]
    z3 = torch.zeros(n, 3, dtype=torch.float64)
    return Particles(position=position, motion=z3.clone(), offset1=z3.clone(), offset2=z3.clone(),
                     color=torch.full((n, 3), 0.7, dtype=torch.float64),
                     transparency=torch.full((n,), 0.8, dtype=torch.float64),
                     template=torch.zeros(n, dtype=torch.long), rotation=torch.zeros(n, dtype=torch.float64),
                     scale=torch.full((n,), 0.6 if not field else 0.15, dtype=torch.float64),
                     defocus=torch.zeros(n, dtype=torch.long), frame="world",
                     settings=RenderSettings(blend="additive", defocus_brighten=False,
                                             templates="test-disc"),
                     optics=FieldOptics(near=0.1, far=50.0, fade=0.0) if field else None)


def wall_pair() -> FramePair:
    g = torch.Generator().manual_seed(0)
    k = torch.tensor([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    eye = torch.eye(4, dtype=torch.float64)
    depth = torch.full((1, H, W), WALL, dtype=torch.float64)
    return FramePair(id=PairId("synthetic", "test", "wall", 1),
                     image1=0.1 + 0.2 * torch.rand(3, H, W, generator=g, dtype=torch.float64),
                     image2=0.1 + 0.2 * torch.rand(3, H, W, generator=g, dtype=torch.float64),
                     depth1=depth, depth2=depth.clone(), intrinsics=k, cam2_from_cam1=eye,
                     cam1_from_world=eye, cam2_from_world=eye)


def along_rays(field: bool, detach: bool):
    """Images and the gradients of a fixed weighting of them with respect to a step ``s`` along
    each particle's camera ray and to the transparencies."""
    pair, rec = wall_pair(), record(field)
    rays = rec.position / rec.position.norm(dim=1, keepdim=True)
    s = torch.zeros(rec.count, dtype=torch.float64, requires_grad=True)
    theta = rec.transparency.clone().requires_grad_(True)
    moved = rec.replace(offset1=s[:, None] * rays, transparency=theta)
    eye = torch.eye(4, dtype=torch.float64)[None]
    out = render(pair.image1[None], pair.image2[None], pair.depth1[None], pair.depth2[None],
                 pair.intrinsics[None], eye, eye, moved, disc_library(), beta=30.0,
                 detach_occlusion=detach)
    weights = torch.rand(out.image1.shape, generator=torch.Generator().manual_seed(1),
                         dtype=torch.float64)
    (out.image1 * weights + out.image2 * weights).sum().backward()
    return out, s.grad, theta.grad


@pytest.mark.parametrize("field", [False, True], ids=["paper-records", "field-records"])
def test_detached_occlusion_passes_no_gradient_to_depth(field):
    full, grad_depth, grad_theta = along_rays(field, detach=False)
    cut, grad_depth_cut, grad_theta_cut = along_rays(field, detach=True)
    # The same forward pass.
    assert torch.equal(full.image1, cut.image1) and torch.equal(full.image2, cut.image2)
    assert torch.equal(full.opacity1, cut.opacity1)
    # Along the rays only V changes: its gradient is there with V attached, gone without (up
    # to the rounding of the projected positions, which move by ~1e-16 px along a ray).
    assert bool((grad_depth.abs() > 1e-6).all()), grad_depth
    assert float(grad_depth_cut.abs().max()) < 1e-10 * float(grad_depth.abs().min())
    # Other gradients are untouched.
    assert torch.allclose(grad_theta, grad_theta_cut, rtol=1e-12, atol=0)


def test_attached_occlusion_gradient_is_the_numerical_one():
    """With V attached the gradient along the rays matches central differences (float64)."""
    def image_sum(s):
        pair, rec = wall_pair(), record(False)
        rays = rec.position / rec.position.norm(dim=1, keepdim=True)
        eye = torch.eye(4, dtype=torch.float64)[None]
        out = render(pair.image1[None], pair.image2[None], pair.depth1[None], pair.depth2[None],
                     pair.intrinsics[None], eye, eye, rec.replace(offset1=s[:, None] * rays),
                     disc_library(), beta=30.0)
        return out.image1.sum() + out.image2.sum()

    s = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    image_sum(s).backward()
    h = 1e-6
    numeric = torch.stack([(image_sum(h * e) - image_sum(-h * e)) / (2 * h)
                           for e in torch.eye(3, dtype=torch.float64)])
    assert torch.allclose(s.grad, numeric, rtol=1e-4, atol=1e-7)
