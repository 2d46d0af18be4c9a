"""Where the depth test reads the scene depth (``RenderSettings.depth_shift``): under ``--compat
reference`` half a pixel up and left of each pixel, as the research code's sampling grid reads
it, checked against the scene depth resampled there by ``grid_sample`` (a half-pixel reference
written here) on a synthetic depth step; weathergen's own convention (at the pixel) otherwise;
the setting travels in the particle file."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from engine_scenes import plane_pair
from weathergen.engine import Particles, RenderSettings, load_templates, render_pair, render_view
from weathergen.engine.sampling.field import pair_views
from weathergen.engine.rendering.renderer import pair_starts
from weathergen.errors import ConfigError, FormatError

NAMES = ("image1", "image2", "opacity1", "opacity2")


def step_pair():
    """A plane at depth 6 with a near box at depth 1 whose top and left edges face the plane;
    the camera moves a little right in frame 2."""
    pair = plane_pair(24, 32, depth=6.0, world=False, dtype=torch.float64)
    pair.depth1[:, 8:18, 10:22] = 1.0
    pair.depth2[:, 8:18, 12:24] = 1.0
    pair.cam2_from_cam1[0, 3] = -0.05
    return pair


def curtain(shift: float) -> Particles:
    """A grid of particles at depth 2.5 (between the box and the mean of box and plane), each
    with its own 5 x 5 flake, covering the box's edges."""
    y, x = torch.meshgrid(torch.linspace(-0.5, 0.5, 9, dtype=torch.float64),
                          torch.linspace(-0.6, 0.6, 11, dtype=torch.float64), indexing="ij")
    n = x.numel()
    position = torch.stack((x.reshape(-1), y.reshape(-1), torch.full((n,), 2.5,
                                                                     dtype=torch.float64)), 1)
    zeros = torch.zeros(n, 3, dtype=torch.float64)
    return Particles(position=position, motion=zeros.clone(), offset1=zeros.clone(),
                     offset2=zeros.clone(), color=torch.full((n, 3), 0.9, dtype=torch.float64),
                     transparency=torch.full((n,), 0.8, dtype=torch.float64),
                     template=torch.zeros(n, dtype=torch.long),
                     rotation=torch.zeros(n, dtype=torch.float64),
                     scale=torch.ones(n, dtype=torch.float64),
                     defocus=torch.zeros(n, dtype=torch.long), frame="camera1",
                     settings=RenderSettings(depth_shift=shift),
                     stamps=torch.ones(n, 5, 5))


def half_pixel_up_left(depth: torch.Tensor) -> torch.Tensor:
    """The depth bilinearly resampled at (x − 0.5, y − 0.5), the border repeated."""
    h, w = depth.shape[-2:]
    y, x = torch.meshgrid(torch.arange(h, dtype=depth.dtype) - 0.5,
                          torch.arange(w, dtype=depth.dtype) - 0.5, indexing="ij")
    grid = torch.stack((2 * x / (w - 1) - 1, 2 * y / (h - 1) - 1), -1)[None]
    return torch.nn.functional.grid_sample(depth[None], grid, mode="bilinear",
                                           padding_mode="border", align_corners=True)[0]


def test_reference_reads_the_depth_half_a_pixel_up_left():
    pair = step_pair()
    shifted = render_pair(pair, curtain(0.5))
    resampled = dataclasses.replace(pair, depth1=half_pixel_up_left(pair.depth1),
                                    depth2=half_pixel_up_left(pair.depth2))
    expected = render_pair(resampled, curtain(0.0))
    at_pixel = render_pair(pair, curtain(0.0))
    for name in NAMES:
        assert float((getattr(shifted, name) - getattr(expected, name)).abs().max()) < 1e-12
    for name in ("image1", "image2"):   # the two conventions differ along the box's edges
        assert float((getattr(shifted, name) - getattr(at_pixel, name)).abs().max()) > 0.1


def test_a_single_view_reads_it_there_too():
    pair, record = step_pair(), curtain(0.5)
    start1, _, disp = pair_starts(record, torch.float64, torch.device("cpu"))
    image, opacity = render_view(pair.image1, pair_views(pair)[0], record, start1, disp,
                                 load_templates("flakes"))
    out = render_pair(pair, record)
    assert float((image - out.image1[0]).abs().max()) < 1e-12
    assert float((opacity - out.opacity1[0]).abs().max()) < 1e-12


def test_compat_sets_the_shift_and_the_file_keeps_it(tmp_path):
    record = curtain(0.0)
    assert record.for_compat("paper") is record
    reference = record.for_compat("reference")
    assert reference.settings.depth_shift == 0.5
    assert reference.for_compat("paper").settings == record.settings
    plain, kept = tmp_path / "plain.npz", tmp_path / "kept.npz"
    record.save(plain)
    reference.save(kept)
    assert "depth_shift" not in str(np.load(plain)["scalars"])     # the default is not written
    assert Particles.load(kept).settings.depth_shift == 0.5
    assert Particles.load(plain).settings.depth_shift == 0.0
    arrays = dict(np.load(kept))
    arrays["scalars"] = np.array(str(arrays["scalars"]).replace("0.5", "1.5"))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(FormatError, match="depth_shift must be in"):
        Particles.load(tmp_path / "bad.npz")
    with pytest.raises(ConfigError, match="depth_shift must be in"):
        RenderSettings(depth_shift=-0.5)
