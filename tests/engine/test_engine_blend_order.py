"""Blur samples blended one after another (``RenderSettings.blur_blend = "sequential"``, what
``--compat reference`` draws for α-blended motion blur): each sample's sums blended over the frame
the earlier samples left, clamped after each, against a per-sample loop written here and the
naive oracle; gradients (float64 gradcheck); the other records of a call keep their bytes; the
setting travels in the particle file."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from engine_scenes import plane_pair, pose, rotation
from oracle import oracle_render
from weathergen.engine import (BETA_ATTACK, BETA_RENDER, Particles, RenderSettings, load_preset,
                               load_templates, render, render_view, sample_particles)
from weathergen.engine.sampling.field import pair_views
from weathergen.engine.rendering.renderer import pair_starts, view_sums
from weathergen.errors import ConfigError, FormatError
from weathergen.framepair import FramePairBatch

NAMES = ("image1", "image2", "opacity1", "opacity2")


def still_pair(h=14, w=20, dtype=torch.float64):
    """A textured plane at depth 2, a still camera (frame 2's streaks are frame 1's, moved)."""
    return plane_pair(h, w, depth=2.0, world=False, dtype=dtype)


def blob(side: int, width: float) -> torch.Tensor:
    y, x = torch.meshgrid(*(torch.arange(side, dtype=torch.float64) - side // 2,) * 2,
                          indexing="ij")
    return torch.exp(-(x * x + y * y) / (2 * width * width))


def crossing(blend="alpha", samples=4, theta=(2.4, 2.2, 1.6, 2.0), dtype=torch.float64,
             order="sequential") -> Particles:
    """Four dark particles at depth 1.2 with their own 5 x 5 flakes whose streaks cross each
    other (θ / K up to 0.6: where they overlap in one sample A > 1, and ``I (1 − A) + C`` falls
    below 0: the clamp acts)."""
    pos = torch.tensor([[-0.12, -0.06, 1.2], [0.1, -0.06, 1.2], [-0.02, 0.08, 1.2],
                        [0.0, -0.02, 1.25]], dtype=dtype)
    motion = torch.tensor([[0.2, 0.1, 0.0], [-0.2, 0.1, 0.0], [0.02, -0.2, 0.0],
                           [0.1, 0.1, 0.05]], dtype=dtype)
    n = 4
    return Particles(
        position=pos, motion=motion, offset1=torch.zeros(n, 3, dtype=dtype),
        offset2=torch.zeros(n, 3, dtype=dtype),
        color=torch.tensor([[0.05, 0.02, 0.0], [0.0, 0.05, 0.02], [0.1, 0.05, 0.0],
                            [0.02, 0.0, 0.05]], dtype=dtype),
        transparency=torch.tensor(theta, dtype=dtype), template=torch.zeros(n, dtype=torch.long),
        rotation=torch.zeros(n, dtype=dtype), scale=torch.ones(n, dtype=dtype),
        defocus=torch.zeros(n, dtype=torch.long), frame="camera1",
        settings=RenderSettings(blend=blend, blur_length=0.6, blur_samples=samples,
                                blur_blend=order),
        stamps=torch.stack([blob(5, w) for w in (1.2, 0.9, 1.5, 1.1)]).float())


def draw(pair, records, beta=BETA_RENDER):
    b = FramePairBatch.stack([pair] * len(records)) if not isinstance(pair, list) else \
        FramePairBatch.stack(pair)
    return render(b.image1, b.image2, b.depth1, b.depth2, b.intrinsics,
                  torch.eye(4, dtype=torch.float64).expand(len(records), 4, 4),
                  b.cam2_from_cam1, records, beta=beta)


def by_hand(pair, record):
    """The frames drawn sample by sample: sample k of every streak as a record of its own (no
    blur, θ / K, from X_t + k s (X2 − X1)), its sums from the engine's splat, blended over the
    frame the earlier samples left and clamped, ``I ← clamp(I (1 − A_k) + C_k, 0, 1)``."""
    s = record.settings
    count, spacing = s.blur_samples, s.blur_length / (s.blur_samples - 1)
    single = record.replace(transparency=record.transparency / count,
                            settings=s.replace(blur_samples=1, blur_length=0.0, blur_blend="sum"))
    start1, start2, disp = pair_starts(record, torch.float64, torch.device("cpu"))
    lib = load_templates("flakes")
    frames, clamped = [], False
    for view, image, start in zip(pair_views(pair), (pair.image1, pair.image2), (start1, start2)):
        out, kept = image.double(), torch.ones(1, *image.shape[1:], dtype=torch.float64)
        for k in range(count):
            a, c = view_sums(view, single, start + k * spacing * disp, torch.zeros_like(disp), lib)
            out = out * (1 - a) + c
            clamped = clamped or bool(((out < 0) | (out > 1)).any())
            out = out.clamp(0, 1)
            kept = kept * (1 - a.clamp(0, 1))
        frames.append((out, 1 - kept))
    return frames, clamped


def test_sample_by_sample_equals_the_loop_written_here_and_differs_from_the_sum():
    pair = still_pair()
    record = crossing()
    out = draw(pair, [record])
    ((image1, opacity1), (image2, opacity2)), clamped = by_hand(pair, record)
    assert clamped                                         # the clamp between samples acts
    for got, want in ((out.image1[0], image1), (out.image2[0], image2),
                      (out.opacity1[0], opacity1), (out.opacity2[0], opacity2)):
        assert float((got - want).abs().max()) < 1e-12
    summed = draw(pair, [record.replace(settings=record.settings.replace(blur_blend="sum"))])
    apart = (out.image1 - summed.image1).abs().amax(1)[0]
    assert float(apart.max()) > 0.05                       # where the streaks overlap
    assert float((apart > 1e-6).double().mean()) < 0.5     # and not elsewhere


def test_sample_by_sample_equals_the_oracle_for_a_sampled_preset():
    """alpha-white's particles (templates, rotations, defocus; its K samples, none added on the
    long streaks), two moving cameras: the core within 1e-9 of the naive oracle."""
    cam1 = pose(rotation(roll_deg=2, pitch_deg=-3))
    cam2 = pose(rotation(roll_deg=2, pitch_deg=-2, yaw_deg=1), centre=(0.05, 0.0, 0.1))
    pair = plane_pair(24, 32, depth=5.0, near_block=True, cam1_from_world=cam1,
                      cam2_from_world=cam2, dtype=torch.float64)
    record = sample_particles(pair, load_preset("alpha-white", {"count": 12, "size": 9,
                                                                "blur_samples": 3}), seed=4)
    record = record.replace(defocus=record.defocus.clamp(max=4)).for_compat("reference")
    assert record.settings.blur_blend == "sequential"
    b = FramePairBatch.stack([pair])
    args = (b.image1, b.image2, b.depth1, b.depth2, b.intrinsics, b.cam1_from_world,
            b.cam2_from_world, [record])
    lib = load_templates("flakes")
    core = render(*args, lib, beta=BETA_RENDER)
    want = oracle_render(*args, lib, beta=BETA_RENDER)
    for name, w in zip(NAMES, want):
        assert float((getattr(core, name) - w).abs().max()) <= 1e-9, name
    summed = render(*args[:-1], [record.for_compat("paper")], lib, beta=BETA_RENDER)
    assert float((core.image1 - summed.image1).abs().max()) > 1e-3


def test_gradcheck_sample_by_sample():
    """float64 gradcheck of the frames and opacities in the offsets, colours and
    transparencies (a few random projections of every output)."""
    pair = still_pair(10, 14)
    base = crossing(samples=3, theta=(0.6, 0.5, 0.4, 0.5))
    g = torch.Generator().manual_seed(0)
    weights = torch.rand(6, 2 * 4 * 10 * 14, generator=g, dtype=torch.float64)

    def f(d1, d2, col, th):
        o = draw(pair, [base.replace(offset1=d1, offset2=d2, color=col, transparency=th)],
                 beta=BETA_ATTACK)
        return weights @ torch.cat([getattr(o, n).reshape(-1) for n in NAMES])

    leaves = [getattr(base, n).clone().requires_grad_(True)
              for n in ("offset1", "offset2", "color", "transparency")]
    assert torch.autograd.gradcheck(f, leaves, eps=1e-6, atol=1e-6)


def test_the_other_records_of_a_call_keep_their_bytes():
    """In a batch with a pair blended sample by sample, the other pairs (α-blended all at
    once, additive) are the bytes they are alone, and so is that pair."""
    pair = still_pair(dtype=torch.float32)
    records = [crossing(dtype=torch.float32), crossing(dtype=torch.float32, order="sum"),
               crossing("additive", dtype=torch.float32, order="sum")]
    batch = draw(pair, records)
    for i, record in enumerate(records):
        alone = draw(pair, [record])
        for name in NAMES:
            assert torch.equal(getattr(batch, name)[i], getattr(alone, name)[0]), (i, name)
    assert not torch.equal(batch.image1[0], batch.image1[1])


def test_a_single_view_blends_sample_by_sample_too():
    pair = still_pair()
    record = crossing()
    start1, _, disp = pair_starts(record, torch.float64, torch.device("cpu"))
    image, opacity = render_view(pair.image1, pair_views(pair)[0], record, start1, disp,
                                 load_templates("flakes"))
    out = draw(pair, [record])
    assert float((image - out.image1[0]).abs().max()) < 1e-12
    assert float((opacity - out.opacity1[0]).abs().max()) < 1e-12


def test_compat_picks_the_blending_and_the_file_keeps_it(tmp_path):
    settings = RenderSettings.from_preset(load_preset("alpha-white"))
    assert settings.blur_blend == "sum" and not settings.blends_in_order
    assert settings.for_compat("reference").blends_in_order
    assert settings.for_compat("reference").for_compat("paper") == settings
    for name in ("snow", "rain", "fog"):          # additive, or alpha without motion blur
        other = RenderSettings.from_preset(load_preset(name))
        assert other.for_compat("reference").blur_blend == "sum"
    pair = still_pair(dtype=torch.float32)
    record = sample_particles(pair, load_preset("alpha-white", {"count": 20}), seed=1)
    assert record.for_compat("paper") is record
    ordered = record.for_compat("reference")
    plain, kept = tmp_path / "plain.npz", tmp_path / "ordered.npz"
    record.save(plain)
    ordered.save(kept)
    assert "blur_blend" not in str(np.load(plain)["scalars"])    # the default is not written
    assert Particles.load(kept).settings == ordered.settings
    assert Particles.load(plain).settings == record.settings
    arrays = dict(np.load(kept))
    arrays["scalars"] = np.array(str(arrays["scalars"]).replace("sequential", "sideways"))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FormatError, match="unknown blur_blend 'sideways'"):
        Particles.load(tmp_path / "bad.npz")
    with pytest.raises(ConfigError, match="blur_blend must be sum or sequential"):
        RenderSettings(blur_blend="sideways")
