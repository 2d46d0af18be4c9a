"""RAFT behind the model contract: padding, shapes, gradients, the paper's conventions, and
the released RAFT-small predicting known flow."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from model_checks import (assert_flow_at_input_size, assert_gradient_reaches_both_images,
                          batch_and_alone, input_gradient, random_frames)
from numerics import assert_float32_close, rounding_k

from weathergen.flow import aee
from weathergen.models import InputPadder, build_model, get_model
from weathergen.models.raft import CorrelationPyramid, bilinear_upsample, convex_upsample



@pytest.fixture(scope="module")
def released_small(raft_small_weights):
    return get_model("raft-small", checkpoint=raft_small_weights, iters=12)


# -- padding ----------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [(436, 1024), (64, 64), (17, 33), (1, 1), (375, 1242)])
def test_padding_round_trips(size):
    h, w = size
    padder = InputPadder(h, w, multiple=8, min_size=64)
    x = torch.rand(2, 3, h, w)
    padded = padder.pad(x)
    ph, pw = padded.shape[-2:]
    assert ph % 8 == 0 and pw % 8 == 0 and ph >= max(h, 64) and pw >= max(w, 64)
    assert ph - h < 8 or h < 64  # no more than needed
    assert 0 <= padder.bottom - padder.top <= 1 and 0 <= padder.right - padder.left <= 1
    assert torch.equal(padder.unpad(padded), x)
    # Replicated border: the first padded row repeats the image's first row.
    assert torch.equal(padded[..., 0, padder.left:padder.left + w], x[..., 0, :])


def test_padding_rejects_other_sizes():
    padder = InputPadder(20, 30)
    with pytest.raises(ValueError, match="expected a tensor of size 20x30"):
        padder.pad(torch.rand(1, 3, 21, 30))
    with pytest.raises(ValueError, match="padded size"):
        padder.unpad(torch.rand(1, 2, 20, 30))


# -- the contract -----------------------------------------------------------------------------

@pytest.mark.parametrize("size", [(20, 30), (67, 93)])
def test_flow_comes_back_at_input_size(size):
    assert_flow_at_input_size(build_model("raft-small", iters=2), size, batch=2)


#: RAFT's chain of sums, forward (tests/numerics.py): the encoder's 14 convolutions, the
#: correlation, 10 per refinement step (lookup, motion encoder, the separable GRU's four
#: convolutions in a chain, the flow head) and the convex upsampling (mask, weighted sum); the
#: longest over 256 x 3 x 3 terms.
RAFT_TERMS = 256 * 9


def raft_sums(iters):
    return 14 + 1 + 10 * iters + 2


def test_batch_elements_are_independent():
    in_batch, alone = batch_and_alone(build_model("raft", iters=2), (64, 80))
    # Equal up to float32 rounding: a batch of two may add in another order.
    assert_float32_close(in_batch, alone, rounding_k(raft_sums(2), RAFT_TERMS))


def test_float64_images_get_float64_flow_with_a_gradient():
    model = build_model("raft-small", iters=1)
    x1 = torch.rand(1, 3, 64, 64, dtype=torch.float64, requires_grad=True)
    flow = model(x1, torch.rand(1, 3, 64, 64, dtype=torch.float64))
    assert flow.dtype == torch.float64
    flow.sum().backward()
    assert x1.grad.dtype == torch.float64 and x1.grad.abs().sum() > 0


def test_bad_inputs_are_rejected_with_shapes():
    model = build_model("raft-small", iters=1)
    expected = r"expected image1 of shape \(B, 3, H, W\), got \(3, 64, 64\)"
    with pytest.raises(ValueError, match=expected):
        model(torch.rand(3, 64, 64), torch.rand(3, 64, 64))
    with pytest.raises(ValueError, match="same shape"):
        model(torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 72))


@pytest.mark.parametrize("arch", ["raft", "raft-small"])
def test_gradient_reaches_both_images(arch):
    assert_gradient_reaches_both_images(build_model(arch, iters=3).requires_grad_(False), (64, 72))


def test_gradient_checkpointing_gives_the_same_gradient():
    torch.manual_seed(0)
    plain = build_model("raft", iters=3)
    recomputing = build_model("raft", iters=3, gradient_checkpointing=True)
    recomputing.load_state_dict(plain.state_dict())
    x1, x2 = random_frames(1, (64, 64))
    grads = [input_gradient(model, x1, x2) for model in (plain, recomputing)]
    # Equal up to float32 rounding (the recomputation may add in another order): the chain of
    # sums forward and back.
    assert_float32_close(grads[1], grads[0], rounding_k(2 * raft_sums(3), RAFT_TERMS))


def test_released_small_has_a_useful_gradient(released_small):
    released_small.iters = 4
    try:
        x1 = torch.rand(1, 3, 64, 64, requires_grad=True)
        x2 = torch.rand(1, 3, 64, 64, requires_grad=True)
        aee(released_small(x1, x2), torch.zeros(1, 2, 64, 64)).sum().backward()
    finally:
        released_small.iters = 12
    assert torch.isfinite(x1.grad).all() and x1.grad.abs().max() > 0
    assert torch.isfinite(x2.grad).all() and x2.grad.abs().max() > 0


# -- conventions of the released models --------------------------------------------------------

def test_correlation_lookup_order_and_values():
    """Level 0 at zero flow: channel a*(2r+1)+b holds <f1(p), f2(p + (a-r, b-r))>/sqrt(D),
    (x offset a slowest), and zero where the window leaves the image."""
    torch.manual_seed(1)
    d, h, w, r = 5, 6, 7, 2
    f1, f2 = torch.randn(2, 1, d, h, w).unbind(0)
    pyramid = CorrelationPyramid(f1, f2, levels=2, radius=r)
    ys, xs = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
    coords = torch.stack([xs, ys])[None]
    out = pyramid.lookup(coords)
    k = 2 * r + 1
    assert out.shape == (1, 2 * k * k, h, w)
    for (y, x) in [(3, 3), (0, 6), (5, 0)]:
        for a in range(k):
            for b in range(k):
                x2, y2 = x + a - r, y + b - r
                inside = 0 <= x2 < w and 0 <= y2 < h
                expected = 0.0
                if inside:
                    expected = float(f1[0, :, y, x] @ f2[0, :, y2, x2]) / math.sqrt(d)
                assert out[0, a * k + b, y, x].item() == pytest.approx(expected, abs=1e-5)


def test_upsampling_keeps_constant_flow():
    flow = torch.tensor([1.5, -0.25]).view(1, 2, 1, 1).expand(1, 2, 5, 6).contiguous()
    coarse = bilinear_upsample(flow)
    assert coarse.shape == (1, 2, 40, 48)
    assert torch.allclose(coarse, 8 * flow[..., :1, :1].expand_as(coarse))
    fine = convex_upsample(flow, torch.randn(1, 9 * 64, 5, 6))
    interior = fine[..., 8:-8, 8:-8]  # at the border the 3x3 window reaches zero padding
    assert torch.allclose(interior, 8 * flow[..., :1, :1].expand_as(interior), atol=1e-5)


# -- the released network predicts real flow ------------------------------------------------------

def _texture(x: torch.Tensor, y: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """A smooth random colour texture defined everywhere in the plane: (3, *x.shape) in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    out = torch.zeros(3, *x.shape, dtype=torch.float64)
    for c in range(3):
        for _ in range(25):
            wavelength = 6 + 30 * torch.rand((), generator=g, dtype=torch.float64)
            angle, phase = 2 * math.pi * torch.rand(2, generator=g, dtype=torch.float64)
            out[c] += torch.sin(2 * math.pi / wavelength
                                * (x * torch.cos(angle) + y * torch.sin(angle)) + phase)
    return (0.5 + out / 12).clamp(0, 1).float()


def test_released_small_recovers_a_subpixel_translation(released_small):
    h, w, (du, dv) = 96, 128, (2.3, -1.6)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64),
                            torch.arange(w, dtype=torch.float64), indexing="ij")
    image1 = _texture(xs, ys)
    image2 = _texture(xs - du, ys - dv)  # frame 2 shows at p + d what frame 1 shows at p
    with torch.no_grad():
        flow = released_small(image1[None], image2[None])
    truth = torch.tensor([du, dv]).view(1, 2, 1, 1).expand_as(flow)
    interior = (slice(None), slice(None), slice(8, -8), slice(8, -8))
    assert aee(flow[interior], truth[interior]).item() < 0.5
    assert aee(flow, truth).item() < 1.0


def test_released_small_on_the_demo_scene_is_close_to_ground_truth(released_small, demo_root):
    from weathergen.datasets import demo_pairs
    from weathergen.io.images import read_raw

    pairs = [p for p in demo_pairs(first_frame=1, frames_per_scene=1)]
    assert len(pairs) >= 2
    for pair in pairs:
        occlusion = read_raw(Path(demo_root) / "training" / "occlusions" / pair.id.scene
                             / f"frame_{pair.id.frame:04d}.png")
        visible = torch.as_tensor(occlusion.reshape(pair.size) == 0)[None]
        with torch.no_grad():
            flow = released_small(pair.image1[None], pair.image2[None])
        truth = pair.flow[None]
        baseline = aee(torch.zeros_like(truth), truth).item()
        assert baseline > 5, "the demo scene should have substantial motion"
        assert aee(flow, truth, visible).item() < 1.0, pair.id
        assert aee(flow, truth).item() < 1.5, pair.id
