"""The paper's published weather as weathergen particles: the research code's particle files
(:mod:`weathergen.io.published_weather`) mapped into a pair's :class:`Particles` record.

The research code holds a particle at ``X1`` in camera-1 coordinates and moves it to
``X2 = R X1 + t + m`` in frame 2 (``R``, ``t`` the pair's relative pose ``cam2_from_cam1``, ``m``
its motion in camera-2 axes). A weathergen record holds ``P`` and ``M`` in the pair's reference
frame (the world, or camera 1) and draws ``X1 = cam1_from_ref P``, ``X2 = cam2_from_ref (P + M)``;
so

    P = cam1_from_ref⁻¹ X1,     M = R2ᵀ m     (R2 the rotation of cam2_from_ref),

which gives ``cam2_from_ref (P + M) = cam2_from_cam1 X1 + m``: the same two camera positions
whenever the pair's ``cam2_from_cam1`` is the research code's (its per-scene depth factors and
its zeroed camera translation in the scenes it scales; see docs/render.md). Each particle keeps
its own flake (the stored alpha, as the record's ``stamps``), colour and transparency
``θ = s (tanh(value) + 1) / 2`` with ``s`` the preset's transparency scale, as the research code
draws it; how particles are blended and blurred comes from the preset (the files do not say).
Offsets start at zero; the template, scale, rotation and defocus of the record are unused. The
stored alpha's slightly negative values (the flake rotation's spline undershoots, down to about
-0.01) are set to 0: the research code cuts them off after shifting the flake to its sub-pixel
position, weathergen before (the difference is below a thousandth of a grey level's worth of
light per flake, see docs/render.md).
"""

from __future__ import annotations

import torch

from ...framepair import FramePair
from ...io.published_weather import PublishedWeather
from ..records.particles import Particles
from ..weather.presets import Preset
from ..common import reference_transforms
from ..records.settings import RenderSettings


def published_particles(weather: PublishedWeather, pair: FramePair, preset: Preset) -> Particles:
    """``weather`` as a record of ``pair`` (in the pair's reference frame), drawn with the
    render settings of ``preset`` (blend, motion blur; its ``transparency`` is the scale ``s``).
    Shape: N particles -> a record of N particles with stamps (N, S, S)."""
    frame, cam1, cam2 = reference_transforms(pair)
    cam1, cam2 = cam1.double().cpu(), cam2.double().cpu()
    x1 = torch.from_numpy(weather.points).double()
    homogeneous = torch.cat([x1, torch.ones(x1.shape[0], 1, dtype=torch.float64)], 1)
    position = (homogeneous @ torch.linalg.inv(cam1).T)[:, :3]
    motion = torch.from_numpy(weather.motion).double() @ cam2[:3, :3]      # R2ᵀ m, row by row
    theta = float(preset.transparency) * (torch.tanh(torch.from_numpy(weather.transparency).double())
                                          + 1) / 2
    n = weather.count
    zeros3 = torch.zeros(n, 3)
    return Particles(position=position.float(), motion=motion.float(), offset1=zeros3,
                     offset2=zeros3.clone(), color=torch.from_numpy(weather.color).float().clone(),
                     transparency=theta.float(), template=torch.zeros(n, dtype=torch.int64),
                     rotation=torch.zeros(n), scale=torch.ones(n),
                     defocus=torch.zeros(n, dtype=torch.int64), frame=frame,
                     settings=RenderSettings.from_preset(preset),
                     stamps=torch.from_numpy(weather.alpha).float().clamp(min=0))
