"""Ground truth of the particle layer of a pair: its flow, its opacity and the flow a viewer sees.

- **Particle flow** ``(2, H, W)``: at every pixel, the opacity-weighted mean of the projected
  displacements (frame 1 to frame 2) of the particles covering it in frame 1,
  ``Σ_i w_i f_i / Σ_i w_i`` with ``w_i = θ_i B_i V_i`` the particle's splatted weight and ``f_i`` the
  displacement of its centre's projection; zero where no particle is. Computed by the render
  core's splat with the displacements in place of the colour (:func:`~weathergen.engine.rendering.renderer.view_sums`).
- **Opacity** ``(1, H, W)``: ``clamp(Σ_i w_i, 0, 1)``, the renderer's opacity of frame 1.

Combined weather (:class:`~weathergen.engine.LayeredParticles`): the particles of every layer
(each layer's sums with its own templates, an additive layer's particles dimmed by the alpha
layers in front of them as the layered render dims them); the particle flow is the weighted mean
over all of them, the opacity that of the layered render,
``1 − Π_l (1 − clamp(Σ_{i in l} w_i, 0, 1))``.
- **Seen flow** ``(2, H, W)``: the particle flow where the particles dominate a pixel
  (opacity >= ``threshold``, 0.5 by default) and the scene's flow elsewhere; valid where the
  particles dominate or the scene's flow is valid.

Which to train on: the scene flow (the dataset's ground truth) teaches a network to see through the
weather, the usual goal of augmentation and of robustness; the seen flow teaches it to report the
motion of whatever is in front, snowflakes included (for tracking what the camera actually
sees, or for evaluating how a network treats the particles); the particle flow with its opacity
trains or evaluates layered models that estimate both motions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Union

import torch

from ...framepair import FramePair
from ...geometry import project, transform_points
from ..common import check_pair_for_engine, reference_transforms
from .combined import layers_view_sums
from ..records.layered import LayeredParticles
from ..records.particles import Particles
from .renderer import BETA_RENDER, pair_starts, view_sums
from ..weather.templates import TemplateLibrary, load_templates
from ..views import View

SEEN_THRESHOLD = 0.5


@dataclass
class ParticleTruth:
    """Shape: flow (2, H, W) pixels; opacity (1, H, W) in [0, 1]; weight (1, H, W) = Σ w_i."""

    flow: torch.Tensor
    opacity: torch.Tensor
    weight: torch.Tensor


def particle_truth(pair: FramePair, particles: Union[Particles, LayeredParticles],
                   templates: Optional[TemplateLibrary] = None, *, beta: float = BETA_RENDER,
                   chunk_elements: Optional[int] = None) -> ParticleTruth:
    """Particle flow and opacity of frame 1 of ``pair`` (float64 accumulation on the CPU);
    over every layer of combined weather (``templates`` then unused: each layer's own)."""
    check_pair_for_engine(pair)
    if isinstance(particles, LayeredParticles):
        layers = particles.to(torch.device("cpu"))
        values = [_flow_values(pair, *_starts(r)[:2]) for r in layers.layers]
        sums = layers_view_sums(_view(pair), layers, values, beta=beta, dtype=torch.float64,
                                device="cpu", chunk_elements=chunk_elements)
        weight = sum(w for w, _ in sums)
        colour = sum(c for _, c in sums)
        clear = torch.stack([1 - w.clamp(0, 1) for w, _ in sums]).prod(0)
        opacity = (1 - clear).clamp(0, 1)
    else:
        weight, colour = _layer_sums(pair, particles, templates, beta, chunk_elements)
        opacity = weight.clamp(0, 1)
    covered = weight > 0
    safe = torch.where(covered, weight, torch.ones_like(weight))
    flow = torch.where(covered, colour[:2] / safe, torch.zeros_like(colour[:2]))
    return ParticleTruth(flow=flow.float(), opacity=opacity.float(), weight=weight.float())


def _layer_sums(pair: FramePair, particles: Particles, templates: Optional[TemplateLibrary],
                beta: float, chunk_elements: Optional[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """One record's ``Σ w`` (1, H, W) and ``Σ w f`` (3, H, W, the third zero) in frame 1."""
    lib = templates if templates is not None else load_templates(particles.settings.templates)
    rec = particles.to(torch.device("cpu"))
    start1, start2, disp = _starts(rec)
    return view_sums(_view(pair), rec, start1, disp, lib, beta=beta,
                     values=_flow_values(pair, start1, start2), dtype=torch.float64,
                     device="cpu", chunk_elements=chunk_elements)


def _starts(rec: Particles) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`pair_starts` of a record on the CPU, in float64."""
    return pair_starts(rec, torch.float64, torch.device("cpu"))


def _view(pair: FramePair) -> View:
    """Frame 1's camera, in float64 on the CPU."""
    _, c1, _ = reference_transforms(pair)
    return View(pair.intrinsics.double().cpu(), c1.double().cpu(), pair.depth1.cpu())


def _flow_values(pair: FramePair, start1: torch.Tensor, start2: torch.Tensor) -> torch.Tensor:
    """Each particle's displacement of its centre's projection from frame 1 (``start1``) to
    frame 2 (``start2``), padded with a zero third channel. Shape: (N, 3) float64."""
    _, c1, c2 = reference_transforms(pair)
    k = pair.intrinsics.double().cpu()
    p1, _ = project(transform_points(c1.double().cpu(), start1), k)
    p2, _ = project(transform_points(c2.double().cpu(), start2), k)
    return torch.cat((p2 - p1, torch.zeros(start1.shape[0], 1, dtype=torch.float64)), 1)


def seen_flow(truth: ParticleTruth, scene_flow: Optional[torch.Tensor],
              scene_valid: Optional[torch.Tensor] = None, threshold: float = SEEN_THRESHOLD
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The flow a viewer sees: the particles' where they dominate, the scene's elsewhere.

    Shape: scene_flow (2, H, W) or None (no scene ground truth: valid only under the particles),
    scene_valid (1, H, W) bool or None (all valid) -> (flow (2, H, W), valid (1, H, W) bool).
    """
    dominant = truth.opacity >= threshold
    if scene_flow is None:
        return torch.where(dominant, truth.flow, torch.zeros_like(truth.flow)), dominant
    valid = torch.ones_like(dominant) if scene_valid is None else scene_valid.bool()
    flow = torch.where(dominant, truth.flow, scene_flow.to(truth.flow.dtype))
    return flow, dominant | valid
