"""Renderer: naive reference comparison (outputs and gradients), gradcheck, invariants, goldens."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from engine_scenes import plane_pair
from weathergen.engine import (BETA_ATTACK, Particles, RenderSettings, TemplateLibrary, from_atanh,
                               load_preset, render, render_pair, sample_particles, to_atanh)
from weathergen.engine.records.particles import empty_particles
from weathergen.engine.sampling.pair import NEAR
from weathergen.engine.rendering.tracks import MAX_BLUR_SAMPLES
from weathergen.errors import ConfigError, DatasetError, WeatherGenError

GOLDEN = Path(__file__).parent / "golden"
REGEN = os.environ.get("WEATHERGEN_REGEN_GOLDEN") == "1"


# -- tiny scenes -----------------------------------------------------------------------------

def blob_library(res: int = 8, asymmetric: bool = True) -> TemplateLibrary:
    """Two small templates: a round Gaussian blob and (optionally) a lopsided one."""
    c = (res - 1) / 2
    yy, xx = torch.meshgrid(torch.arange(res, dtype=torch.float64),
                            torch.arange(res, dtype=torch.float64), indexing="ij")
    r2 = (xx - c) ** 2 + (yy - c) ** 2
    blob = torch.exp(-r2 / (0.15 * res * res))
    lop = torch.exp(-((xx - c - 1) ** 2 + 3 * (yy - c) ** 2) / (0.1 * res * res))
    alphas = torch.stack((blob, lop if asymmetric else blob))
    alphas = alphas * (r2 <= (res / 2) ** 2)
    return TemplateLibrary(name="test-blobs", alphas=alphas.float(), digest="")


def tiny_pair(dtype=torch.float64, depth=2.0, h=12, w=16):
    return plane_pair(h, w, depth=depth, world=False, dtype=dtype)


def tiny_particles(dtype=torch.float64, blur=3, blend="additive", defocus=(0, 2, 0),
                   z=(1.2, 1.9, 1.5)) -> Particles:
    """Three particles in front of a plane, camera-1 coordinates, with known footprints."""
    pos = torch.tensor([[-0.35, -0.2, z[0]], [0.3, 0.1, z[1]], [0.05, 0.25, z[2]]], dtype=dtype)
    motion = torch.tensor([[0.05, 0.08, 0.0], [-0.04, 0.06, 0.1], [0.0, 0.1, -0.05]], dtype=dtype)
    return Particles(
        position=pos, motion=motion,
        offset1=torch.tensor([[0.01, -0.02, 0.0], [0.0, 0.01, 0.02], [-0.01, 0.0, 0.01]], dtype=dtype),
        offset2=torch.tensor([[0.0, 0.01, -0.01], [0.02, 0.0, 0.0], [0.01, -0.01, 0.0]], dtype=dtype),
        color=torch.tensor([[0.9, 0.8, 0.7], [0.2, 0.5, 0.9], [0.6, 0.6, 0.1]], dtype=dtype),
        transparency=torch.tensor([0.7, 0.5, 0.9], dtype=dtype),
        template=torch.tensor([0, 1, 1]), rotation=torch.tensor([0.3, 2.0, -1.1], dtype=dtype),
        scale=torch.tensor([5.4, 2.6, 3.3], dtype=dtype) / 8,
        defocus=torch.tensor(defocus), frame="camera1",
        settings=RenderSettings(blend=blend, blur_length=0.5 if blur > 1 else 0.0,
                                blur_samples=blur, defocus_brighten=True, templates="test-blobs"))


def fast(pair, parts, lib, beta):
    return render(pair.image1[None], pair.image2[None], pair.depth1[None], pair.depth2[None],
                  pair.intrinsics[None], torch.eye(4, dtype=torch.float64)[None],
                  pair.cam2_from_cam1[None], [parts], lib, beta=beta)


# -- a naive reference renderer: plain loops, written from the model's equations --------------

def _naive_level(alphas: np.ndarray, level: int) -> np.ndarray:
    out = alphas
    for _ in range(level):
        t, r, _ = out.shape
        half = np.zeros((t, r // 2, r // 2))
        for i in range(r // 2):
            for j in range(r // 2):
                half[:, i, j] = out[:, 2 * i:2 * i + 2, 2 * j:2 * j + 2].mean(axis=(1, 2))
        out = half
    return out


def _naive_stamp(lib, tid, rotation, scale, radius, brighten):
    """The particle's alpha stamp around its centre, as its phases P and a dict
    {(dy, dx): value} of its values at (dy, dx) / P pixels from the centre: the template
    rotated and scaled to the footprint, each value the mean of sub x sub samples over the pixel
    square centred there (4 x 4 for stamps up to 5 pixels wide, 2 x 2 up to 9). Stamps up to 9
    pixels without a disc blur are sampled every 1 / sub pixel (P = sub), others at whole
    pixels (P = 1)."""
    res = lib.resolution
    footprint = max(scale * res, 1.0)
    side = 2 * max(math.floor(footprint / 2 + 0.5), 1) + 1
    sub = 4 if side <= 5 else (2 if side <= 9 else 1)
    level = 0
    while level + 1 <= 3 and res / (footprint * sub) >= 2 ** (level + 1) \
            and (res >> level) % 2 == 0 and (res >> level) >= 4:
        level += 1
    tmpl = _naive_level(lib.alphas.double().numpy(), level)[tid]
    rl = tmpl.shape[0]
    half = int(math.ceil(footprint / 2)) + 2
    phases = sub if radius <= 1 else 1
    stamp = {}
    for dy in range(-half * phases, half * phases + 1):
        for dx in range(-half * phases, half * phases + 1):
            total = 0.0
            for iy in range(sub):
                for ix in range(sub):
                    sy = dy / phases + (iy + 0.5) / sub - 0.5
                    sx = dx / phases + (ix + 0.5) / sub - 0.5
                    # template offset = Rot(-rotation) * image offset, in half-footprints
                    xn = (math.cos(rotation) * sx + math.sin(rotation) * sy) / (footprint / 2)
                    yn = (-math.sin(rotation) * sx + math.cos(rotation) * sy) / (footprint / 2)
                    if xn * xn + yn * yn > 1:
                        continue
                    px, py = (xn + 1) / 2 * rl - 0.5, (yn + 1) / 2 * rl - 0.5
                    x0, y0 = math.floor(px), math.floor(py)
                    for yy, wy in ((y0, 1 - (py - y0)), (y0 + 1, py - y0)):
                        for xx, wx in ((x0, 1 - (px - x0)), (x0 + 1, px - x0)):
                            if 0 <= yy < rl and 0 <= xx < rl:
                                total += wy * wx * tmpl[yy, xx]
            if total:
                stamp[(dy, dx)] = total / (sub * sub)
    if radius > 1:
        disc = [(a, b) for a in range(-radius, radius + 1) for b in range(-radius, radius + 1)
                if a * a + b * b <= radius * radius]
        blurred = {}
        for dy in range(-half - radius, half + radius + 1):
            for dx in range(-half - radius, half + radius + 1):
                v = sum(stamp.get((dy - a, dx - b), 0.0) for a, b in disc) / len(disc)
                blurred[(dy, dx)] = min(max(2 * v, 0.0) ** (1 / 3), 1.0) if brighten else v
        stamp = blurred
        if brighten:          # softened: a b x b box twice (a tent (b − |k|) / b² per axis)
            b = 2 * (radius // 4 + 2) + 1
            reach = half + radius + b - 1
            tent = {k: (b - abs(k)) / b ** 2 for k in range(1 - b, b)}
            stamp = {(dy, dx): sum(tent[a] * tent[c] * blurred.get((dy - a, dx - c), 0.0)
                                   for a in tent for c in tent)
                     for dy in range(-reach, reach + 1) for dx in range(-reach, reach + 1)}
    return phases, stamp


def _naive_samples(k, x, along, length: float, preset: int) -> int:
    """Blur samples of the streak x + s along, s in [0, length] (camera coordinates): one more
    than its length in pixels at its nearer end's pixel speed, at least the preset's, at most
    MAX_BLUR_SAMPLES. (The numerator of d(X/Z)/ds is constant along a line.)"""
    if preset <= 1:
        return preset
    x, a = [float(t) for t in x], [float(t) for t in along]
    z_near = max(min(x[2], x[2] + length * a[2]), NEAR)
    speed = math.hypot(float(k[0, 0]) * (a[0] * x[2] - x[0] * a[2]),
                       float(k[1, 1]) * (a[1] * x[2] - x[1] * a[2])) / z_near ** 2
    return min(max(math.ceil(length * speed) + 1, preset), MAX_BLUR_SAMPLES)


def naive_render(pair, parts: Particles, lib, beta):
    h, w = pair.size
    k = pair.intrinsics
    images = [pair.image1, pair.image2]
    depths = [pair.depth1[0], pair.depth2[0]]
    out, opac = [], []
    for t in range(2):
        alpha = [[0.0] * w for _ in range(h)]
        colour = [[[0.0] * w for _ in range(h)] for _ in range(3)]
        for j in range(parts.count):
            phases, stamp = _naive_stamp(lib, int(parts.template[j]), float(parts.rotation[j]),
                                         float(parts.scale[j]), int(parts.defocus[j]),
                                         parts.settings.defocus_brighten)
            # the streak runs along the camera-space motion X2 - X1 (own + camera motion)
            p1 = parts.position[j] + parts.offset1[j]
            p2 = p1 + parts.motion[j] + parts.offset2[j]
            c2 = pair.cam2_from_cam1.to(p1.dtype)
            x1, x2 = p1, c2[:3, :3] @ p2 + c2[:3, 3]
            preset = parts.settings.blur_samples if parts.settings.blur_length > 0 else 1
            kk = _naive_samples(k, (x1 if t == 0 else x2).detach(), (x2 - x1).detach(),
                                parts.settings.blur_length, preset)
            for s in range(kk):
                frac = parts.settings.blur_length * s / (kk - 1) if kk > 1 else 0.0
                x = (x1 if t == 0 else x2) + frac * (x2 - x1)
                u = k[0, 0] * x[0] / x[2] + k[0, 2]
                v = k[1, 1] * x[1] / x[2] + k[1, 2]
                theta = parts.transparency[j] / kk
                for py in range(h):
                    for px in range(w):
                        # the stamp at the pixel's offset from (u, v), bilinear between its
                        # values 1 / P pixel apart (on a grid point: the interval that a larger
                        # u, v moves into, the core's one-sided derivative)
                        gx, gy = (px - u) * phases, (py - v) * phases
                        x0 = math.ceil(float(gx.detach())) - 1
                        y0 = math.ceil(float(gy.detach())) - 1
                        corners = [stamp.get((y0 + a, x0 + b), 0.0) for a in (0, 1)
                                   for b in (0, 1)]
                        if not any(corners):
                            continue
                        wx, wy = gx - x0, gy - y0
                        acc = (1 - wy) * ((1 - wx) * corners[0] + wx * corners[1]) \
                            + wy * ((1 - wx) * corners[2] + wx * corners[3])
                        vis = 1 / (1 + torch.exp(beta * (x[2] - depths[t][py, px])))
                        a = acc * vis * theta
                        alpha[py][px] = alpha[py][px] + a
                        for c in range(3):
                            colour[c][py][px] = colour[c][py][px] + a * parts.color[j, c]
        a_img = torch.stack([torch.stack([torch.as_tensor(v, dtype=torch.float64) for v in row])
                             for row in alpha])[None]
        c_img = torch.stack([torch.stack([torch.stack([torch.as_tensor(v, dtype=torch.float64)
                                                       for v in row]) for row in colour[c]])
                             for c in range(3)])
        img = images[t].double()
        blended = img * (1 - a_img) + c_img if parts.settings.blend == "alpha" else img + c_img
        out.append(blended.clamp(0, 1))
        opac.append(a_img.clamp(0, 1))
    return out, opac


@pytest.mark.parametrize("blend,blur,defocus", [("additive", 3, (0, 2, 0)), ("alpha", 1, (3, 0, 0))])
def test_fast_renderer_matches_naive_reference_outputs_and_gradients(blend, blur, defocus):
    pair, lib = tiny_pair(), blob_library()
    base = tiny_particles(blur=blur, blend=blend, defocus=defocus)
    leaves = {name: getattr(base, name).clone().requires_grad_(True)
              for name in ("offset1", "offset2", "color", "transparency")}
    gen = torch.Generator().manual_seed(3)
    upstream = [torch.randn(3, 12, 16, generator=gen, dtype=torch.float64) for _ in range(2)]

    def run(renderer):
        for leaf in leaves.values():
            leaf.grad = None
        parts = base.replace(**leaves)
        if renderer == "fast":
            o = fast(pair, parts, lib, BETA_ATTACK)
            images, opac = [o.image1[0], o.image2[0]], [o.opacity1[0], o.opacity2[0]]
        else:
            images, opac = naive_render(pair, parts, lib, BETA_ATTACK)
        loss = sum((img * g).sum() for img, g in zip(images, upstream))
        loss.backward()
        return ([x.detach() for x in images + opac],
                {k: v.grad.clone() for k, v in leaves.items()})

    fast_out, fast_grad = run("fast")
    ref_out, ref_grad = run("naive")
    for a, b in zip(fast_out, ref_out):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-7)
    assert float(fast_out[2].max()) > 0.05  # the scene really shows particles
    for name in leaves:
        torch.testing.assert_close(fast_grad[name], ref_grad[name], atol=1e-8, rtol=1e-6)
        assert float(fast_grad[name].abs().sum()) > 0


@pytest.mark.parametrize("name", ["offset1", "offset2", "color", "transparency"])
def test_gradcheck(name):
    pair, lib = tiny_pair(), blob_library()
    base = tiny_particles(blur=2)

    def f(x):
        o = fast(pair, base.replace(**{name: x}), lib, BETA_ATTACK)
        return o.image1, o.image2, o.opacity1, o.opacity2

    x = getattr(base, name).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-6)


def test_gradcheck_in_atanh_domain():
    pair, lib = tiny_pair(), blob_library()
    base = tiny_particles(blur=1, blend="alpha")
    eta_c = to_atanh(base.color).clone().requires_grad_(True)
    eta_t = to_atanh(base.transparency).clone().requires_grad_(True)

    def f(ec, et):
        o = fast(pair, base.replace(color=from_atanh(ec), transparency=from_atanh(et)), lib,
                 BETA_ATTACK)
        return o.image1, o.image2

    assert torch.autograd.gradcheck(f, (eta_c, eta_t), eps=1e-6, atol=1e-6)
    torch.testing.assert_close(from_atanh(to_atanh(base.color)), base.color, atol=2e-6, rtol=0)


def test_atanh_helpers_stay_strictly_inside():
    xi = from_atanh(torch.tensor([-1e4, 0.0, 1e4], dtype=torch.float64))
    assert bool((xi > 0).all() and (xi < 1).all())
    assert torch.isfinite(to_atanh(torch.tensor([0.0, 1.0]))).all()


# -- invariants ----------------------------------------------------------------------------

def test_no_particles_or_zero_transparency_leaves_frames_unchanged():
    pair = plane_pair(24, 32, world=False)
    for blend in ("additive", "alpha"):
        out = render_pair(pair, empty_particles("camera1", RenderSettings(blend=blend)))
        assert torch.equal(out.image1[0], pair.image1) and torch.equal(out.image2[0], pair.image2)
        assert not bool(out.opacity1.any())
        parts = sample_particles(pair, load_preset("snow", {"count": 50, "blend": blend}), 0)
        out = render_pair(pair, parts.replace(transparency=torch.zeros_like(parts.transparency)))
        assert torch.equal(out.image1[0], pair.image1) and torch.equal(out.image2[0], pair.image2)


def test_particle_behind_surface_changes_nothing():
    pair, lib = tiny_pair(torch.float32, depth=1.0), blob_library()
    parts = tiny_particles(torch.float32, z=(1.8, 1.9, 2.5))  # all behind the plane at depth 1
    out = fast(pair, parts, lib, 250.0)
    assert torch.equal(out.image1[0], pair.image1) and torch.equal(out.image2[0], pair.image2)
    visible = fast(tiny_pair(torch.float32, depth=5.0), parts, lib, 250.0)
    assert float(visible.opacity1.sum()) > 0


def test_particle_at_rest_with_still_camera_lands_on_the_same_pixels():
    pair, lib = tiny_pair(torch.float32), blob_library()
    parts = tiny_particles(torch.float32, blur=1)
    zero = torch.zeros_like(parts.motion)
    parts = parts.replace(motion=zero, offset1=zero, offset2=zero)
    out = fast(pair, parts, lib, 250.0)
    assert float(out.opacity1.sum()) > 0
    assert torch.equal(out.opacity1, out.opacity2)


def test_displacement_equals_projected_motion():
    """A round particle's opacity centroid sits at its projection; hand-computed for both frames."""
    pair = plane_pair(64, 80, depth=10.0, world=False, dtype=torch.float64)
    move = torch.eye(4, dtype=torch.float64)
    move[:3, 3] = torch.tensor([-0.1, 0.05, 0.2], dtype=torch.float64)  # camera 2 moved
    pair.cam2_from_cam1 = move
    lib = blob_library(asymmetric=False)
    p, m = (0.2, -0.1, 2.0), (0.05, 0.15, -0.1)
    parts = tiny_particles(blur=1).select(torch.tensor([0])).replace(
        position=torch.tensor([p], dtype=torch.float64),
        motion=torch.tensor([m], dtype=torch.float64),
        offset1=torch.zeros(1, 3, dtype=torch.float64), offset2=torch.zeros(1, 3, dtype=torch.float64),
        scale=torch.tensor([7.0 / 8], dtype=torch.float64), defocus=torch.tensor([0]),
        transparency=torch.tensor([0.3], dtype=torch.float64))
    out = fast(pair, parts, lib, 250.0)
    f, cx, cy = 0.8 * 80, 79 / 2, 63 / 2
    x1 = p
    x2 = (p[0] + m[0] - 0.1, p[1] + m[1] + 0.05, p[2] + m[2] + 0.2)
    expected = [(f * x[0] / x[2] + cx, f * x[1] / x[2] + cy) for x in (x1, x2)]
    ys, xs = torch.meshgrid(torch.arange(64.0, dtype=torch.float64),
                            torch.arange(80.0, dtype=torch.float64), indexing="ij")
    for opac, (eu, ev) in zip((out.opacity1[0, 0], out.opacity2[0, 0]), expected):
        total = opac.sum()
        assert abs(float((opac * xs).sum() / total) - eu) < 1e-9
        assert abs(float((opac * ys).sum() / total) - ev) < 1e-9


def test_batch_equals_single_renders():
    pairs = [plane_pair(24, 32, world=False, seed=s, near_block=True) for s in (0, 1)]
    parts = [sample_particles(p, load_preset("sparks", {"count": 80}), seed=s)
             for s, p in enumerate(pairs)]
    from weathergen.framepair import FramePairBatch
    batch = render_pair(FramePairBatch.stack(pairs), parts)
    for i in range(2):
        single = render_pair(pairs[i], parts[i])
        torch.testing.assert_close(batch.image1[i], single.image1[0], atol=1e-6, rtol=0)
        torch.testing.assert_close(batch.opacity2[i], single.opacity2[0], atol=1e-6, rtol=0)


def test_render_errors():
    pair = plane_pair(24, 32, world=True)
    parts = sample_particles(pair, load_preset("snow", {"count": 10}), 0)
    with pytest.raises(ConfigError, match="world coordinates"):
        render_pair(plane_pair(24, 32, world=False), parts)
    with pytest.raises(ConfigError, match="digest"):
        render_pair(pair, parts.replace(settings=parts.settings.replace(templates_digest="0" * 16)))
    with pytest.raises(DatasetError, match="depth"):
        render(pair.image1[None], pair.image2[None], None, pair.depth2[None],
               pair.intrinsics[None], torch.eye(4)[None], torch.eye(4)[None], [parts])
    if not torch.cuda.is_available():
        with pytest.raises(WeatherGenError, match="CUDA is not available"):
            render_pair(pair, parts, device="cuda")


# -- golden images -------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["snow", "rain", "sparks", "fog"])
def test_golden_images(name):
    pair = plane_pair(48, 64, depth=2.5, near_block=True)
    overrides = {"count": 6} if name == "fog" else {"count": 150}
    parts = sample_particles(pair, load_preset(name, overrides), seed=7)
    out = render_pair(pair, parts)
    img = torch.cat((out.image1[0], out.image2[0]), dim=2)
    got = (img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
    path = GOLDEN / f"{name}.png"
    import cv2
    if REGEN:
        GOLDEN.mkdir(exist_ok=True)
        cv2.imwrite(str(path), got[..., ::-1])
        pytest.skip(f"regenerated {path}")
    want = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert want is not None, f"{path} missing: run with WEATHERGEN_REGEN_GOLDEN=1"
    diff = np.abs(got.astype(int) - want[..., ::-1].astype(int))
    assert diff.max() <= 2 and diff.mean() < 0.05, f"{name}: max diff {diff.max()}"
    assert (got != (torch.cat((pair.image1, pair.image2), 2).permute(1, 2, 0).numpy() * 255
                    + 0.5).astype(np.uint8)).any()


# -- cost ----------------------------------------------------------------------------------

def test_memory_kept_for_backward_does_not_grow_with_the_footprints():
    """Autograd may keep a few numbers per blur sample, not the patches of every stamp pixel."""
    pair, lib = tiny_pair(torch.float32, depth=5.0, h=48, w=64), blob_library()
    base = tiny_particles(torch.float32, blur=20)
    base = base.replace(scale=torch.full((3,), 61.0 / 8))            # 61-pixel stamps
    leaves = {name: getattr(base, name).clone().requires_grad_(True)
              for name in ("offset1", "offset2", "color", "transparency")}
    seen: dict = {}

    def pack(t):
        seen[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes()
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = fast(pair, base.replace(**leaves), lib, BETA_ATTACK)
    # Keeping the patches costs tens of bytes per patch pixel; the frames and the per-sample
    # numbers the backward pass needs fit in well under one byte per patch pixel here.
    from weathergen.engine import build_stamps
    sides = build_stamps([base], lib).side                 # 61 px, the defocused one softened
    patch_pixels = 2 * 20 * int(((sides + 1) ** 2).sum())            # frames x K x patches
    assert sum(seen.values()) < patch_pixels, sum(seen.values())
    (out.image1.sum() + out.image2.sum()).backward()
    assert all(float(leaf.grad.abs().sum()) > 0 for leaf in leaves.values())


def test_each_stamp_is_as_large_as_its_footprint_not_the_template():
    """Far particles get a few pixels, near ones their full size: cost follows the footprint."""
    from weathergen.engine import build_stamps, load_templates
    lib = load_templates("flakes")                                  # 80-pixel templates
    footprints = torch.tensor([1.0, 2.5, 7.0, 20.0, 71.0])
    parts = tiny_particles(torch.float32).select(torch.tensor([0, 0, 0, 0, 0])).replace(
        scale=footprints / lib.resolution, defocus=torch.zeros(5, dtype=torch.int64),
        template=torch.zeros(5, dtype=torch.int64), settings=RenderSettings(templates="flakes"))
    stamps = build_stamps([parts], lib)
    sides = stamps.side
    assert bool((sides >= footprints).all())                         # the whole footprint fits
    assert bool((sides <= 1.2 * footprints + 3).all()), sides.tolist()  # and little more


@pytest.mark.parametrize("rotation", [0.0, math.pi / 2, math.pi, 3 * math.pi / 2, 0.25])
def test_rim_of_an_even_footprint_does_not_depend_on_rounding(rotation):
    """Rim samples of an even-sized footprint lie exactly on the template's circle: whether they are
    drawn must not depend on float32 against float64 (or CPU against GPU rounding)."""
    from weathergen.engine.rendering.stamps import build
    from weathergen.engine.rendering.tracks import Looks

    lib = TemplateLibrary(name="ones", alphas=torch.ones(1, 16, 16), digest="")
    looks = Looks(footprint=torch.tensor([10.0], dtype=torch.float64),
                  defocus=torch.tensor([0]), rotation=torch.tensor([rotation], dtype=torch.float64),
                  template=torch.tensor([0]), brighten=torch.tensor([False]))
    masks = []
    for dtype in (torch.float32, torch.float64):
        stamps = build(looks, lib, dtype=dtype)
        side = int(stamps.side[0])
        assert side == 11
        stamp = stamps.pixels.view(side + 2, side + 2)[1:-1, 1:-1]
        masks.append(stamp > 0)
    assert torch.equal(masks[0], masks[1])
    # the four rim points on the axes, at exactly 5 px from the centre, are drawn
    for y, x in ((5, 0), (5, 10), (0, 5), (10, 5)):
        assert masks[0][y, x] and masks[1][y, x]
