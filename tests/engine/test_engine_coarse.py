"""The coarse path for large billboards (fog): close to the exact render, differentiable."""

from __future__ import annotations

import torch

from engine_scenes import plane_pair
from test_engine_render import blob_library, tiny_pair, tiny_particles
from weathergen.engine import (BETA_ATTACK, build_stamps, load_preset, load_templates, render,
                               render_pair, sample_particles)
from weathergen.engine.stamps import COARSE_MIN_SIDE, COARSE_SIDE


def test_fog_on_the_coarse_grid_stays_close_to_the_exact_render():
    """Tolerance (documented in docs/engine.md): mean absolute difference <= 1/255, 99 % of
    the pixels within 10/255, and away from depth edges every pixel within 20/255 (billboard
    rims and defocus radii are resolved on the coarse grid); near a depth edge a band of about
    f pixels differs more (the coarse grid averages the scene depth over f x f blocks)."""
    pair = plane_pair(218, 512, depth=6.0, near_block=True)
    parts = sample_particles(pair, load_preset("fog", {"count": 8}), seed=3)
    stamps = build_stamps([parts], load_templates(parts.settings.templates))
    assert bool((stamps.coarse >= 2).all())                      # every fog billboard is coarse
    exact = render_pair(pair, parts, coarse_side=None)
    fast = render_pair(pair, parts)
    for a, b in ((exact.image1, fast.image1), (exact.image2, fast.image2)):
        diff = (a - b).abs() * 255
        assert float(diff.mean()) <= 1.0, float(diff.mean())
        assert float(diff.flatten().quantile(0.99)) <= 10.0
        # away from the near block's edge (x = 170) the two agree closely everywhere
        far = torch.cat((diff[..., :, :146], diff[..., :, 194:]), -1)
        assert float(far.max()) <= 20.0, float(far.max())
    assert float((exact.image1 - pair.image1).abs().mean()) * 255 > 10   # fog is really there


def test_small_stamps_never_take_the_coarse_path():
    """Snow, rain and sparks stamps (at most 71 + 2 x 20 pixels) are rendered exactly."""
    assert COARSE_SIDE > 71 + 2 * 20 and COARSE_MIN_SIDE >= 16
    pair = plane_pair(48, 64, depth=2.5, near_block=True)
    parts = sample_particles(pair, load_preset("snow", {"count": 300}), seed=1)
    a, b = render_pair(pair, parts), render_pair(pair, parts, coarse_side=None)
    assert torch.equal(a.image1, b.image1) and torch.equal(a.image2, b.image2)


def test_gradcheck_through_the_coarse_path():
    """Positions, colours and transparencies of particles drawn on a 2x coarser grid."""
    pair, lib = tiny_pair(), blob_library()
    base = tiny_particles(blur=2)
    stamps = build_stamps([base], lib, dtype=torch.float64, coarse_side=2)
    assert bool((stamps.coarse == 1).all())
    g = torch.Generator().manual_seed(0)
    weights = torch.rand(8, 2 * 4 * 12 * 16, generator=g, dtype=torch.float64)

    def f(d1, d2, col, th):
        o = render(pair.image1[None], pair.image2[None], pair.depth1[None], pair.depth2[None],
                   pair.intrinsics[None], torch.eye(4, dtype=torch.float64)[None],
                   pair.cam2_from_cam1[None],
                   [base.replace(offset1=d1, offset2=d2, color=col, transparency=th)], lib,
                   beta=BETA_ATTACK, stamps=stamps)
        flat = torch.cat([t.reshape(-1) for t in (o.image1, o.image2, o.opacity1, o.opacity2)])
        return weights @ flat                      # a few random projections of every output

    leaves = [getattr(base, n).clone().requires_grad_(True)
              for n in ("offset1", "offset2", "color", "transparency")]
    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-6)
