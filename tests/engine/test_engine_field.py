"""Weather fields: geometry of the per-frame looks, frame identity between pairs, density, stereo,
particle ground truth, presets and storage."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from engine_scenes import pose, rotation
from weathergen.engine import (Particles, TemplateLibrary, load_preset, load_templates,
                               render_pair, sample_particles, sample_weather)
from weathergen.engine.sampling.field import (field_for_pair, frame_particles, make_field,
                                              pair_views, sample_field_particles, scene_seed)
from weathergen.datasets import DATASETS, DemoDataset
from weathergen.engine.weather.presets import FieldPreset, preset_from_values
from weathergen.engine.rendering.groundtruth import particle_truth, seen_flow
from weathergen.engine.weather.optics import FieldOptics
from weathergen.engine.records.settings import RenderSettings
from weathergen.engine.rendering.renderer import render_view
from weathergen.engine.views import View, coc_radius, fade, footprint, view_mask
from weathergen.errors import ConfigError
from weathergen.framepair import FramePair, PairId
from weathergen.geometry import project, transform_points

H, W = 40, 56
F = 50.0
K = torch.tensor([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)
#: The pairs here are the demo dataset's: its reader's frame rate.
RATE = DemoDataset.frame_rate


def disc_library(res: int = 16) -> TemplateLibrary:
    """One solid disc: its rendered support measures the footprint."""
    c = (res - 1) / 2
    yy, xx = torch.meshgrid(torch.arange(res, dtype=torch.float64),
                            torch.arange(res, dtype=torch.float64), indexing="ij")
    disc = (((xx - c) ** 2 + (yy - c) ** 2) <= (res / 2) ** 2).float()
    return TemplateLibrary(name="test-disc", alphas=disc[None], digest="")


def field_preset(**over) -> FieldPreset:
    values = {"model": "field", "density": 20.0, "diameter": 0.05, "diameter_jitter": 0.0,
              "near": 0.3, "far": 6.0, "fade": 0.0, "aperture": 0.0, "tile": 2.0,
              "fall_speed": 0.0, "transparency": 1.0}
    values.update(over)
    return preset_from_values("snow", "preset snow (test)", values)


def forward_cameras(n: int, step: float = 0.4):
    """cam_from_world of a camera moving along world +z (OpenCV axes, world = camera 0)."""
    return [pose(rotation(), (0.0, 0.0, step * i)) for i in range(n)]


def wall_depth(cam: torch.Tensor, wall_z: float) -> torch.Tensor:
    """Depth of a fronto-parallel wall at world z = wall_z seen by a camera looking along +z."""
    centre_z = float(torch.linalg.inv(cam)[2, 3])
    return torch.full((1, H, W), wall_z - centre_z, dtype=torch.float32)


def seq_pair(cams, depths, n: int, scene="seq") -> FramePair:
    g = torch.Generator().manual_seed(n)
    img = lambda: (0.2 + 0.3 * torch.rand(3, H, W, generator=g)).float()  # noqa: E731
    return FramePair(id=PairId("demo", "training", scene, n), image1=img(), image2=img(),
                     depth1=depths[n], depth2=depths[n + 1], intrinsics=K.clone(),
                     cam2_from_cam1=cams[n + 1] @ torch.linalg.inv(cams[n]),
                     cam1_from_world=cams[n], cam2_from_world=cams[n + 1])


def one_particle_record(position, motion=(0.0, 0.0, 0.0), diameter=0.1, blur=0.0, samples=1,
                        optics=None) -> Particles:
    z3 = torch.zeros(1, 3)
    return Particles(position=torch.tensor([position], dtype=torch.float32),
                     motion=torch.tensor([motion], dtype=torch.float32), offset1=z3,
                     offset2=z3.clone(), color=torch.ones(1, 3), transparency=torch.ones(1),
                     template=torch.zeros(1, dtype=torch.long), rotation=torch.zeros(1),
                     scale=torch.tensor([diameter]), defocus=torch.zeros(1, dtype=torch.long),
                     frame="world",
                     settings=RenderSettings(blend="additive", blur_length=blur,
                                             blur_samples=samples, defocus_brighten=False,
                                             templates="test-disc"),
                     optics=optics or FieldOptics(near=0.1, far=50.0, fade=0.0))


def centroid(alpha: torch.Tensor) -> tuple[float, float]:
    a = alpha[0].double()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64),
                            torch.arange(W, dtype=torch.float64), indexing="ij")
    return float((a * xs).sum() / a.sum()), float((a * ys).sum() / a.sum())


def render_one(record, cam, depth=None, start=None):
    view = View(K, cam, depth if depth is not None else torch.full((1, H, W), 100.0))
    image = torch.zeros(3, H, W)
    s = start if start is not None else record.position
    return render_view(image, view, record, s, record.motion, disc_library(), beta=250.0,
                       chunk_elements=1 << 20)


# -- geometry of one particle -------------------------------------------------------------------

def test_static_particle_lands_on_its_reprojected_pixel_in_every_frame():
    point = (0.13, -0.07, 3.0)
    record = one_particle_record(point, diameter=0.12)
    cams = [pose(rotation(roll_deg=4 * i, yaw_deg=-3 * i), (0.05 * i, 0.02 * i, 0.3 * i))
            for i in range(5)]
    for cam in cams:
        _, alpha = render_one(record, cam)
        pix, _ = project(transform_points(cam, torch.tensor([point], dtype=torch.float64)), K)
        cx, cy = centroid(alpha)
        assert abs(cx - float(pix[0, 0])) < 0.05 and abs(cy - float(pix[0, 1])) < 0.05


def test_footprint_ratio_is_the_inverse_depth_ratio():
    record = one_particle_record((0.0, 0.0, 4.0), diameter=0.6)
    sizes = []
    for cam in (pose(rotation()), pose(rotation(), (0, 0, 2.0))):      # 4 units away, then 2
        _, alpha = render_one(record, cam)
        sizes.append(math.sqrt(float((alpha > 0.5).sum()) * 4 / math.pi))  # disc diameter, px
    assert sizes[0] == pytest.approx(F * 0.6 / 4.0, abs=0.8)
    assert sizes[1] / sizes[0] == pytest.approx(4.0 / 2.0, rel=0.08)
    assert footprint(F, torch.tensor([0.6]), torch.tensor([2.0])).item() == pytest.approx(15.0)


def test_appearance_functions():
    optics = FieldOptics(near=0.5, far=10.0, fade=0.2, aperture=0.02, focus=2.0)
    z = torch.tensor([0.5, 0.75, 1.0, 5.0, 8.0, 9.0, 10.0], dtype=torch.float64)
    faded = fade(optics.near, optics.far, optics.fade, z)
    assert faded[0] == 0 and faded[-1] == 0 and faded[2] == 1 and faded[3] == 1 and faded[4] == 1
    assert 0 < faded[1] < 1 and 0 < faded[5] < 1
    # thin-lens circle of confusion: 0.5 f A |1/z - 1/focus|, in whole pixels
    r = coc_radius(100.0, optics.aperture, optics.focus, torch.tensor([2.0, 0.5, 0.25], dtype=torch.float64))
    assert r.tolist() == [0, round(0.5 * 100 * 0.02 * 1.5), round(0.5 * 100 * 0.02 * 3.5)]


def test_stereo_disparity_is_f_baseline_over_depth():
    baseline = 0.3
    for z in (1.5, 3.0):
        record = one_particle_record((0.1, 0.05, z), diameter=0.08)
        left = pose(rotation())
        right = pose(rotation(), (baseline, 0.0, 0.0))     # the right camera sits at +x
        _, a_left = render_one(record, left)
        _, a_right = render_one(record, right)
        disparity = centroid(a_left)[0] - centroid(a_right)[0]
        assert disparity == pytest.approx(F * baseline / z, abs=0.05)
        assert centroid(a_left)[1] == pytest.approx(centroid(a_right)[1], abs=0.02)


def test_particle_behind_a_surface_is_not_drawn():
    record = one_particle_record((0.0, 0.0, 3.0), diameter=0.3)
    near_wall = torch.full((1, H, W), 2.0)
    image, alpha = render_one(record, pose(rotation()), depth=near_wall)
    assert float(alpha.sum()) == 0 and float(image.abs().sum()) == 0
    _, alpha = render_one(record, pose(rotation()), depth=torch.full((1, H, W), 4.0))
    assert float(alpha.sum()) > 0


def test_streak_follows_the_exposure():
    record = one_particle_record((0.0, 0.0, 2.0), motion=(0.4, 0.0, 0.0), diameter=0.02,
                                 blur=0.5, samples=21)
    _, alpha = render_one(record, pose(rotation()))
    cols = torch.nonzero(alpha[0].sum(0) > 1e-3).squeeze(1)
    # the streak spans 0.5 x 0.4 units at depth 2: 5 px, plus a footprint of 0.5 px
    assert float(cols.max() - cols.min()) == pytest.approx(F * 0.2 / 2.0, abs=1.5)


# -- the field: frames shared by pairs, density -------------------------------------------------

def sequence(n=5, wall=8.0, step=0.4):
    cams = forward_cameras(n, step)
    depths = [wall_depth(c, wall) for c in cams]
    return cams, depths


def test_frame_is_bit_identical_in_the_two_pairs_that_share_it():
    cams, depths = sequence(4)
    preset = field_preset(density=40.0, fall_speed=0.7, wind=[0.3, -0.2], angle_jitter=20.0,
                          speed_jitter=0.3, exposure=0.02, blur_samples=4, templates="flakes",
                          aperture=0.01, fade=0.2)
    seed = scene_seed(0, "demo", "training", "seq")
    a, b = seq_pair(cams, depths, 1), seq_pair(cams, depths, 2)
    b = dataclasses.replace(b, image1=a.image2.clone())       # the same frame 2 image on disk
    rec_a = sample_field_particles(a, preset, seed, world_up="-y", frame_rate=RATE)
    rec_b = sample_field_particles(b, preset, seed, world_up="-y", frame_rate=RATE)
    assert rec_a.count > 50 and rec_b.count > 50
    out_a, out_b = render_pair(a, rec_a), render_pair(b, rec_b)
    assert torch.equal(out_a.image2, out_b.image1)
    assert torch.equal(out_a.opacity2, out_b.opacity1)
    assert float(out_a.opacity2.sum()) > 0
    # and a sequence frame rendered alone (one view) is the same image
    fld = field_for_pair(b, preset, seed, world_up="-y", frame_rate=RATE)
    view = pair_views(b)[0]
    alone = frame_particles(fld, view, 2)
    image, _ = render_view(b.image1, view, alone, alone.position, alone.motion,
                           load_templates("flakes"), beta=250.0, chunk_elements=1 << 21)
    assert torch.equal(image, out_b.image1[0])


def test_visible_density_stays_constant_over_a_forward_moving_sequence():
    density, near, far = 30.0, 0.3, 5.0
    preset = field_preset(density=density, near=near, far=far, fall_speed=0.5, tile=1.5)
    cams, depths = sequence(8, wall=7.5, step=0.5)     # the wall comes within `far` at frame 6
    fld = make_field(preset, 3, down=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                     frame_rate=10.0, frame="world")
    counts = []
    for n, (cam, depth) in enumerate(zip(cams, depths)):
        view = View(K, cam, depth)
        rec = frame_particles(fld, view, n)
        pts = transform_points(cam, rec.position.double())
        pix, z = project(pts, K)
        inside = (pix[:, 0] >= -0.5) & (pix[:, 0] < W - 0.5) & (pix[:, 1] >= -0.5) \
            & (pix[:, 1] < H - 0.5)
        z_end = min(far, float(depth[0, 0, 0]))
        counted = int((inside & (z >= near) & (z <= z_end)).sum())
        volume = (z_end ** 3 - near ** 3) / 3 * (W / F) * (H / F)   # empty frustum
        expected = density * volume
        counts.append((counted, expected))
        assert abs(counted - expected) < 4 * math.sqrt(expected) + 2, (n, counted, expected)
    # the wall cuts the last frames' volume, and the counts follow it
    assert counts[-1][1] < counts[0][1] * 0.9
    ratio = [c / e for c, e in counts]
    assert max(ratio) - min(ratio) < 0.25


def test_near_wall_hides_the_weather_instead_of_concentrating_it():
    cams = forward_cameras(2, step=0.2)
    wall = [wall_depth(c, 0.8) for c in cams]          # a wall 0.8 ahead of camera 1
    pair = seq_pair(cams, wall, 0)
    preset = field_preset(density=200.0, near=0.2, far=5.0)
    rec = sample_field_particles(pair, preset, 1, world_up="-y", frame_rate=RATE)
    z = transform_points(cams[0], rec.position.double())[:, 2]
    # only the strip of space in front of the wall holds particles, at the field's density
    assert float(z.max()) <= 0.8 + 3 * preset.depth_softness + 0.05
    expected = 200.0 * (0.8 ** 3 - 0.2 ** 3) / 3 * (W / F) * (H / F)
    seen = ((z >= 0.2) & (z <= 0.8)).sum()
    assert int(seen) < 2.5 * expected + 10


# -- ground truth ----------------------------------------------------------------------------

def test_splatted_particle_flow_is_its_projected_displacement():
    cams = forward_cameras(2, step=0.2)
    depths = [torch.full((1, H, W), 50.0) for _ in cams]
    pair = seq_pair(cams, depths, 0)
    record = one_particle_record((0.2, -0.1, 2.5), motion=(0.15, 0.1, 0.0), diameter=0.2)
    truth = particle_truth(pair, record, disc_library())
    p1, _ = project(transform_points(cams[0], torch.tensor([[0.2, -0.1, 2.5]], dtype=torch.float64)), K)
    p2, _ = project(transform_points(cams[1], torch.tensor([[0.35, 0.0, 2.5]], dtype=torch.float64)), K)
    expect = (p2 - p1)[0]
    covered = truth.weight[0] > 0
    assert int(covered.sum()) > 10
    assert torch.allclose(truth.flow[0][covered], torch.full_like(truth.flow[0][covered], float(expect[0])), atol=1e-4)
    assert torch.allclose(truth.flow[1][covered], torch.full_like(truth.flow[1][covered], float(expect[1])), atol=1e-4)
    assert float(truth.flow[:, ~covered].abs().max()) == 0
    # seen flow: the particle's where it dominates, the scene's elsewhere
    scene = torch.full((2, H, W), 7.0)
    seen, valid = seen_flow(truth, scene)
    dominant = truth.opacity[0] >= 0.5
    assert int(dominant.sum()) > 0
    assert torch.equal(seen[:, dominant], truth.flow[:, dominant])
    assert bool((seen[:, ~dominant] == 7.0).all()) and bool(valid.all())


def test_particle_flow_of_two_overlapping_particles_is_their_weighted_mean():
    cams = forward_cameras(2, step=0.0)
    depths = [torch.full((1, H, W), 50.0) for _ in cams]
    pair = seq_pair(cams, depths, 0)
    a = one_particle_record((0.0, 0.0, 2.0), motion=(0.2, 0.0, 0.0), diameter=0.3)
    b = one_particle_record((0.0, 0.0, 2.0), motion=(0.0, 0.1, 0.0), diameter=0.3)
    both = a.replace(**{f: torch.cat((getattr(a, f), getattr(b, f))) for f in
                        ("position", "motion", "offset1", "offset2", "color", "transparency",
                         "template", "rotation", "scale", "defocus")})
    both = both.replace(transparency=torch.tensor([0.75, 0.25]))
    truth = particle_truth(pair, both, disc_library())
    centre = truth.flow[:, H // 2, W // 2]
    assert float(centre[0]) == pytest.approx(0.75 * F * 0.2 / 2.0, abs=1e-3)
    assert float(centre[1]) == pytest.approx(0.25 * F * 0.1 / 2.0, abs=1e-3)


# -- storage, gradients, presets ------------------------------------------------------------

def test_field_record_round_trips_and_rerenders_bit_identically(tmp_path):
    cams, depths = sequence(2)
    pair = seq_pair(cams, depths, 0)
    preset = field_preset(density=30.0, exposure=0.05, blur_samples=3, fall_speed=1.0)
    rec = sample_weather(pair, preset, 5, world_up="-y", frame_rate=RATE)
    path = rec.save(tmp_path / "p.npz")
    with np.load(path) as data:         # version 5: the optics among the gathered 0-d entries
        assert int(data["format_version"]) == 5 and "optics" in json.loads(str(data["scalars"]))
        assert data["position"].dtype == np.float32
    again = Particles.load(path)
    assert again.optics == rec.optics
    a, b = render_pair(pair, rec), render_pair(pair, again)
    assert torch.equal(a.image1, b.image1) and torch.equal(a.image2, b.image2)


def test_paper_records_are_compact_and_without_optics(tmp_path):
    cams, depths = sequence(2)
    pair = seq_pair(cams, depths, 0)
    rec = sample_particles(pair, load_preset("snow", {"count": "20"}), 0)
    with np.load(rec.save(tmp_path / "p.npz")) as data:
        assert int(data["format_version"]) == 5 and "optics" not in json.loads(str(data["scalars"]))
        assert data["position"].dtype == np.uint16


def test_gradients_reach_the_offsets_of_field_records():
    cams, depths = sequence(2)
    pair = seq_pair(cams, depths, 0)
    rec = sample_weather(pair, field_preset(density=30.0), 2, world_up="-y", frame_rate=RATE)
    d1 = rec.offset1.clone().requires_grad_()
    d2 = rec.offset2.clone().requires_grad_()
    colour = rec.color.clone().requires_grad_()
    out = render_pair(pair, rec.replace(offset1=d1, offset2=d2, color=colour), beta=30.0)
    (out.image1.sum() + 2 * out.image2.sum()).backward()
    for g in (d1.grad, d2.grad, colour.grad):
        assert g is not None and float(g.abs().sum()) > 0


def test_field_preset_validation_and_frame_rates():
    p = field_preset()
    assert isinstance(p, FieldPreset) and p.model == "field"
    assert p.frame_rate_for(10.0) == 10.0 and p.frame_rate_for(24.0) == 24.0   # the dataset's
    assert field_preset(frame_rate=60.0).frame_rate_for(10.0) == 60.0          # the preset's wins
    assert field_preset(frame_rate=60.0).frame_rate_for(None) == 60.0
    with pytest.raises(ConfigError, match="needs a frame rate"):
        p.frame_rate_for(None)
    assert field_preset(exposure=1.0).streak_fraction(24.0) == 1.0
    with pytest.raises(ConfigError, match="far"):
        field_preset(near=2.0, far=1.0)
    with pytest.raises(ConfigError, match="unknown key 'count'"):
        preset_from_values("snow", "preset snow (test)", {"model": "field", "count": 5})
    with pytest.raises(ConfigError, match="density"):
        field_preset(density=-1.0)
    with pytest.raises(ConfigError, match="particles per tile"):
        field_preset(density=1e4, tile=100.0)


def test_view_mask_keeps_rim_particles_whose_stamp_reaches_the_image():
    optics = FieldOptics(near=0.1, far=10.0, fade=0.0)
    view = View(K, pose(rotation()), torch.full((1, H, W), 20.0))
    # centre 3 px left of the image, at depth 1: footprint 0.2 * 50 = 10 px, radius 5
    x = (-3.5 - K[0, 2].item()) / F
    pts = torch.tensor([[x, 0.0, 1.0], [x * 4, 0.0, 1.0]], dtype=torch.float64)
    keep = view_mask(view, pts, torch.zeros(2, 3, dtype=torch.float64),
                     torch.tensor([0.2, 0.2], dtype=torch.float64), optics)
    assert keep.tolist() == [True, False]


def test_depth_windows_read_the_farthest_depth_of_the_aligned_blocks_holding_a_window():
    """Against a loop over the pixels: the window's side n, the smallest power of two s >= n,
    the maximum over the s x s blocks (aligned to multiples of s) the window touches; never
    less than the window's own maximum."""
    from weathergen.engine.views import depth_windows

    g = torch.Generator().manual_seed(3)
    depth = torch.rand(2, 1, 13, 21, generator=g, dtype=torch.float64)
    m = 300
    first = torch.stack((torch.randint(0, 21, (m,), generator=g),
                         torch.randint(0, 13, (m,), generator=g)), -1)
    last = torch.minimum(first + torch.randint(0, 14, (m, 1), generator=g),
                         torch.tensor([20, 12]))
    view = torch.randint(0, 2, (m,), generator=g)
    got = depth_windows(depth).farthest(torch.stack((first, last)), view)
    for i in range(m):
        (c0, r0), (c1, r1), d = first[i].tolist(), last[i].tolist(), depth[view[i], 0]
        s = 1
        while s < max(c1 - c0, r1 - r0) + 1:
            s *= 2
        blocks = d[r0 // s * s:(r1 // s + 1) * s, c0 // s * s:(c1 // s + 1) * s]
        assert float(got[i]) == float(blocks.max()) >= float(d[r0:r1 + 1, c0:c1 + 1].max())


def test_the_samplers_own_pixel_first_view_mask_keeps_what_the_renders_keeps():
    """With the view's depth windows given (the sampler: own pixel first, the window only for
    points behind the scene there) the mask is the render's (every window at once)."""
    from weathergen.engine.views import view_windows

    g = torch.Generator().manual_seed(5)
    depth = torch.full((1, H, W), 8.0)
    depth[:, 10:30, 5:25] = 1.5
    depth[:, :, 40:] = 3.0
    view = View(K, pose(rotation()), depth)
    m = 2000
    z = 0.5 + 9 * torch.rand(m, generator=g, dtype=torch.float64)
    uv = torch.rand(m, 2, generator=g, dtype=torch.float64) * torch.tensor([W + 20.0, H + 20.0]) \
        - 10
    pts = torch.stack(((uv[:, 0] - K[0, 2]) / F * z, (uv[:, 1] - K[1, 2]) / F * z, z), 1)
    streak = 0.05 * torch.randn(m, 3, generator=g, dtype=torch.float64)
    diameter = 0.02 + 0.3 * torch.rand(m, generator=g, dtype=torch.float64)
    optics = FieldOptics(near=0.1, far=10.0, fade=0.0, depth_softness=0.05)
    direct = view_mask(view, pts, streak, diameter, optics)
    staged = view_mask(view, pts, streak, diameter, optics, view_windows(view))
    assert torch.equal(direct, staged)
    assert 0.2 < float(direct.double().mean()) < 0.9


def test_view_mask_keeps_clouds_behind_a_wall_whose_stamp_reaches_past_its_edge():
    """A near wall covers the columns left of 28; particles at depth 5 behind it (more than three
    depth softnesses) are drawn only if their stamp reaches past the wall's edge (the farthest
    scene depth within the stamp's reach, not the depth under the centre, decides)."""
    optics = FieldOptics(near=0.1, far=10.0, fade=0.0, depth_softness=0.2)
    depth = torch.full((1, H, W), 20.0)
    depth[:, :, :28] = 1.0
    view = View(K, pose(rotation()), depth)
    z = 5.0
    # footprint 0.6 * 50 / 5 = 6 px: the stamp reaches 0.5 * 6 + 2 = 5 px from the centre
    columns = torch.tensor([24.0, 26.0, 10.0, 4.0])
    x = (columns - K[0, 2]) / F * z
    pts = torch.stack((x, torch.zeros(4, dtype=torch.float64),
                       torch.full((4,), z, dtype=torch.float64)), 1)
    keep = view_mask(view, pts, torch.zeros(4, 3, dtype=torch.float64),
                     torch.full((4,), 0.6, dtype=torch.float64), optics)
    assert keep.tolist() == [True, True, False, False]
    # the same particles ten times nearer (in front of the wall) are all drawn
    near = view_mask(view, pts * 0.1, torch.zeros(4, 3, dtype=torch.float64),
                     torch.full((4,), 0.06, dtype=torch.float64), optics)
    assert near.tolist() == [True] * 4


# -- the bundled ladder ---------------------------------------------------------------------

LADDER = [f"{kind}-{level}" for kind in ("snow", "rain", "sparks", "fog")
          for level in ("light", "moderate", "heavy")]


def test_severity_ladder_is_bundled_and_ordered():
    """Snow, rain and sparks grow in particles; fog (and mist before it) grows in extinction,
    snow and rain in both."""
    from weathergen.engine import list_presets

    assert sorted(LADDER + ["mist"]) == list_presets("field")
    for kind in ("snow", "rain", "sparks"):
        d = [load_preset(f"{kind}-{lvl}").density for lvl in ("light", "moderate", "heavy")]
        assert d[0] < d[1] < d[2]
        assert load_preset(f"{kind}-light").to_dict()["model"] == "field"
    for kind in ("snow", "rain", "fog"):
        beta = [load_preset(f"{kind}-{lvl}").extinction for lvl in ("light", "moderate", "heavy")]
        assert 0 < beta[0] < beta[1] < beta[2]
    assert load_preset("mist").extinction < load_preset("fog-light").extinction
    assert all(load_preset(f"fog-{lvl}").density == 0 for lvl in ("light", "moderate", "heavy"))


@pytest.mark.parametrize("name", [n for n in LADDER if not n.startswith(("snow", "fog"))])
@pytest.mark.parametrize("frame_rate", sorted({cls.frame_rate for cls in DATASETS.values()}))
def test_streaks_of_the_ladder_are_continuous(name, frame_rate):
    """A streak is drawn as blur samples along it; samples further apart than the particle is wide
    draw a dotted line (rain close to the camera, as in indoor RGB-D scenes, showed it)."""
    preset = load_preset(name)
    fld = make_field(preset, 0, down=torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
                     frame_rate=frame_rate)
    assert fld.streak > 0
    length = torch.linalg.vector_norm(fld.step.double() * fld.quantum, dim=1) * fld.streak
    spacing = length / (preset.blur_samples - 1)
    assert bool((spacing <= fld.diameter).all()), float((spacing / fld.diameter).max())


def test_presets_command_names_the_model():
    from click.testing import CliRunner

    from weathergen.cli import presets_cmd  # noqa: F401  (registers the command)
    from weathergen.cli.main import cli

    result = CliRunner().invoke(cli, ["presets"])
    assert result.exit_code == 0, result.output
    for name in LADDER:
        assert f" {name} " in result.output and "field model" in result.output
    assert "paper model" in result.output
    result = CliRunner().invoke(cli, ["presets", "snow-heavy"])
    assert result.exit_code == 0 and "(field model)" in result.output and "density" in result.output


# -- stereo ------------------------------------------------------------------------------------

def test_warped_right_depth_of_a_plane_and_an_occluder():
    from weathergen.engine.rendering.stereo import warp_view_depth

    baseline = 0.2
    right_from_left = torch.eye(4, dtype=torch.float64)
    right_from_left[0, 3] = -baseline          # the right camera sits at +x of the left one
    depth = torch.full((1, H, W), 4.0)
    depth[..., 20:30, 20:30] = 2.0             # a near block
    right = warp_view_depth(depth, None, K, right_from_left, fill=99.0)[0]
    shift_far, shift_near = F * baseline / 4.0, F * baseline / 2.0      # 2.5 and 5 px
    assert float(right[0, 5, 30]) == 4.0                                 # plain plane
    assert float(right[0, 25, 20 - round(shift_near) + 2]) == 2.0       # the block moved left
    assert float(right[0, 5, W - 1]) == 99.0                             # nothing seen there
    assert int((right[0, 5] == 99.0).sum()) == math.floor(shift_far)      # the strip at the edge
    assert bool((right[0, 5, : W - 3] == 4.0).all())                     # no cracks


def test_a_particle_behind_a_completed_tree_is_hidden():
    """A tree reaches above a scanner's top beam: left unknown (at the far depth) a flake behind
    it is drawn in front of it; completed (its column extended upward) the tree hides it."""
    from weathergen.datasets.depth import complete_depth
    from weathergen.framepair import COMPLETED, UNKNOWN

    exact = np.full((H, W), 8.0, np.float32)                # a wall
    exact[:, 24:32] = 3.0                                   # a tree trunk, all the way up
    rng = np.random.default_rng(0)
    image = (np.array([0.35, 0.25, 0.15]) + 0.1 * rng.random((H, W, 3))).astype(np.float32)  # brown
    measured = np.zeros((H, W), bool)
    measured[20::2, ::2] = True                             # nothing above row 20
    seen = []
    for gap in (0.0, 24.0):
        depth, prov = complete_depth(exact, measured, image, far_depth=1000.0, max_gap_px=gap)
        assert (prov[:20, 24:32] == (UNKNOWN if gap == 0 else COMPLETED)).all()
        u, v, z = 28.0, 8.0, 5.0                            # behind the tree, in front of the wall
        point = ((u - float(K[0, 2])) * z / F, (v - float(K[1, 2])) * z / F, z)
        _, alpha = render_one(one_particle_record(point, diameter=0.2), pose(rotation(), (0, 0, 0)),
                              torch.from_numpy(depth)[None])
        seen.append(float(alpha.sum()))
    assert seen[0] > 0.5 and seen[1] == 0.0, seen


def test_right_view_disocclusions_take_the_background_never_the_sky():
    """Beside a near block the right view sees background the left one hid, and at its right
    border what the left never saw: those holes take the farther side's depth along the row (the
    plane behind), not the far depth; the provenance follows each pixel (filled holes completed)."""
    from weathergen.engine.rendering.stereo import warp_view_depth
    from weathergen.framepair import COMPLETED, MEASURED, SKY

    right_from_left = torch.eye(4, dtype=torch.float64)
    right_from_left[0, 3] = -0.2
    depth = torch.full((1, H, W), 4.0)
    depth[..., :10, :] = 1000.0                # the sky
    depth[..., 20:30, 20:30] = 2.0             # a near block
    provenance = torch.zeros((1, H, W), dtype=torch.uint8)
    provenance[..., :10, :] = SKY
    right, kind = warp_view_depth(depth, provenance, K, right_from_left)
    holes = warp_view_depth(depth, None, K, right_from_left, fill=-1.0)[0][0] == -1.0
    ground = holes.clone()
    ground[:11] = False                        # (row 10 also takes row 9's sky: the 2x2 splat)
    assert int(ground[20:30].sum(dim=1).min()) >= 2       # beside the block and at the border
    assert bool((right[0][ground] == 4.0).all()) and bool((kind[0][ground] == COMPLETED).all())
    assert float(right[0, 11:].max()) == 4.0              # nothing below the sky at the far depth
    assert bool((kind[0, :10] == SKY).all()) and bool((right[0, :10] == 1000.0).all())
    assert bool((kind[0, 11:][~holes[11:]] == MEASURED).all())
    torch.testing.assert_close(warp_view_depth(depth, None, K, right_from_left)[0], right)


@pytest.mark.cuda
def test_the_right_views_depth_and_provenance_on_cuda_are_the_cpus():
    from weathergen.engine.rendering.stereo import warp_view_depth
    from weathergen.framepair import SKY

    right_from_left = torch.eye(4, dtype=torch.float64)
    right_from_left[0, 3] = -0.2
    depth = torch.full((1, H, W), 4.0)
    depth[..., :10, :] = 1000.0
    depth[..., 20:30, 20:30] = 2.0
    provenance = torch.zeros((1, H, W), dtype=torch.uint8)
    provenance[..., :10, :] = SKY
    cpu = warp_view_depth(depth, provenance, K, right_from_left)
    gpu = warp_view_depth(depth.cuda(), provenance.cuda(), K.cuda(), right_from_left.cuda())
    assert gpu[0].device.type == "cuda"
    assert torch.equal(gpu[0].cpu(), cpu[0]) and torch.equal(gpu[1].cpu(), cpu[1])


def test_right_camera_renders_the_same_field_particles_at_their_disparity():
    from weathergen.engine.rendering.stereo import render_right, stereo_view, warp_view_depth

    baseline = 0.25
    cams, depths = sequence(2)
    pair = seq_pair(cams, depths, 0)
    record = one_particle_record((0.1, 0.0, 2.5), diameter=0.1)
    right_from_left = torch.eye(4, dtype=torch.float64)
    right_from_left[0, 3] = -baseline
    left = View(K, cams[0], pair.depth1)
    right = stereo_view(left, right_from_left, warp_view_depth(pair.depth1, None, K, right_from_left)[0])
    assert torch.allclose(right.cam_from_ref, right_from_left @ cams[0])
    _, a_left = render_view(torch.zeros(3, H, W), left, record, record.position, record.motion,
                            disc_library(), beta=250.0, chunk_elements=1 << 20)
    _, a_right = render_right(torch.zeros(3, H, W), right, record, record.position,
                              record.motion, disc_library())
    assert centroid(a_left)[0] - centroid(a_right)[0] == pytest.approx(F * baseline / 2.5, abs=0.05)


# -- the views' tests on the render's device ---------------------------------------------------

def test_a_fields_views_tested_on_the_cpu_by_name_give_todays_record():
    from weathergen.engine.records.particles import TENSOR_FIELDS

    from engine_scenes import plane_pair

    pair = plane_pair(64, 96, near_block=True)
    preset = load_preset("snow-light")
    a = sample_field_particles(pair, preset, 3, frame_rate=24.0)
    b = sample_field_particles(pair, preset, 3, frame_rate=24.0, sample_on="cpu")
    assert a.count > 0
    assert all(torch.equal(getattr(a, n), getattr(b, n)) for n in TENSOR_FIELDS)


@pytest.mark.cuda
def test_a_fields_views_tested_on_cuda_give_the_cpus_particles():
    from engine_scenes import plane_pair

    pair = plane_pair(436, 1024, near_block=True)
    preset = load_preset("snow-light")
    cpu = sample_field_particles(pair, preset, 3, frame_rate=24.0)
    gpu = sample_field_particles(pair.to("cuda"), preset, 3, frame_rate=24.0, sample_on="cuda",
                                 device="cuda")
    assert gpu.position.device.type == "cuda" and cpu.count > 100
    assert abs(gpu.count - cpu.count) <= max(2, cpu.count // 200)
    if gpu.count == cpu.count:
        same = (gpu.position.cpu() == cpu.position).all(1)
        assert float(same.float().mean()) > 0.99
