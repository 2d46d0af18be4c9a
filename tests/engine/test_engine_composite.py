"""The renderer's full-resolution steps with hand-written backward passes (engine/rendering/planes.py
and engine/rendering/composite.py) against the plain torch expressions they replace."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from weathergen.engine.rendering.composite import blend
from weathergen.engine.rendering.planes import upsample, upsample_adjoint


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_upsampling_is_bilinear_interpolation_cropped(factor):
    g = torch.Generator().manual_seed(factor)
    grid = torch.rand(3, 1, 5, 7, generator=g, dtype=torch.float64)
    full = F.interpolate(grid, scale_factor=factor, mode="bilinear", align_corners=False)
    assert torch.allclose(upsample(grid, factor, (5 * factor, 7 * factor)), full, atol=1e-14)
    size = (5 * factor - factor // 2, 7 * factor - 1)        # the image is not whole blocks
    assert torch.allclose(upsample(grid, factor, size), full[..., :size[0], :size[1]], atol=1e-14)


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_upsampling_adjoint_is_the_transpose(factor):
    """<up(x), y> = <x, up*(y)> for random x, y; equal to autograd's gradient of interpolate."""
    g = torch.Generator().manual_seed(10 + factor)
    x = torch.rand(2, 1, 4, 6, generator=g, dtype=torch.float64, requires_grad=True)
    y = torch.rand(2, 1, 4 * factor, 6 * factor, generator=g, dtype=torch.float64)
    ref, = torch.autograd.grad(F.interpolate(x, scale_factor=factor, mode="bilinear",
                                             align_corners=False), x, y)
    assert torch.allclose(upsample_adjoint(y, factor), ref, atol=1e-12)
    assert torch.autograd.gradcheck(lambda t: upsample(t, factor, (4 * factor - 1, 6 * factor - 3)),
                                     (x,), eps=1e-6, atol=1e-8)
    # a gradient cropped along either axis, both or neither (each order of the two passes)
    for size in ((4 * factor, 6 * factor), (4 * factor - 1, 6 * factor),
                 (4 * factor, 6 * factor - 3), (4 * factor - 1, 6 * factor - 3)):
        crop = y[..., :size[0], :size[1]]
        ref, = torch.autograd.grad(F.interpolate(x, scale_factor=factor, mode="bilinear",
                                                 align_corners=False)[..., :size[0], :size[1]],
                                   x, crop)
        got, = torch.autograd.grad(upsample(x, factor, size), x, crop)
        assert torch.allclose(got, ref, atol=1e-12), size


def _reference_blend(sums, image1, image2, alpha_mode):
    outs, ops = [], []
    mode = alpha_mode.view(-1, 1, 1, 1)
    for t, image in enumerate((image1, image2)):
        alpha, colour = sums[0, t], sums[1:, t, :, 0].transpose(0, 1)
        pre = torch.where(mode, image * (1 - alpha) + colour, image + colour)
        outs.append(pre.clamp(0, 1))
        ops.append(alpha.clamp(0, 1))
    return (*outs, *ops)


@pytest.mark.parametrize("modes", [(True, True), (False, False), (True, False)])
def test_blending_matches_the_expression_and_its_gradient(modes):
    g = torch.Generator().manual_seed(sum(modes))
    b, h, w = 2, 5, 6
    # values around the clamp limits, none exactly on them
    sums = (torch.rand(4, 2, b, 1, h, w, generator=g, dtype=torch.float64) * 1.2 - 0.1)
    images = [torch.rand(b, 3, h, w, generator=g, dtype=torch.float64) for _ in range(2)]
    alpha_mode = torch.tensor(modes)
    got = blend(sums, *images, alpha_mode)
    want = _reference_blend(sums, *images, alpha_mode)
    for a, e in zip(got, want):
        assert torch.allclose(a, e, atol=1e-15)
    leaves = [sums.clone().requires_grad_(True)] + [i.clone().requires_grad_(True) for i in images]
    weights = [torch.rand(o.shape, generator=g, dtype=torch.float64) for o in want]

    def loss(fn, s, i1, i2):
        return sum((o * wt).sum() for o, wt in zip(fn(s, i1, i2, alpha_mode), weights))

    grads = torch.autograd.grad(loss(blend, *leaves), leaves)
    ref = torch.autograd.grad(loss(_reference_blend, *leaves), leaves)
    for a, e in zip(grads, ref):
        assert torch.allclose(a, e, atol=1e-12)
