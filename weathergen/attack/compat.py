"""The paper's attack or the research code's: the terms in which they differ, in one place.

weathergen follows the paper by default (``compat="paper"``: its equations, Section 3.2, and the
supplement's tables). ``compat="reference"`` does what the authors' research code
(``attack_weather.py``, ``weather_attack/render.py``, ``helper_functions/losses.py`` of
cv-stuttgart/DistractingDownpour) does instead, so that its published tables can be reproduced.
The terms, each switched here and nowhere else:

- **gradient reset**: the research code clears the gradients once before its loop, so every
  step's backward pass adds to the earlier ones and Adam is fed ``Σ_{i ≤ k} ∇L_i``
  (:func:`resets_gradients`);
- **occlusion**: it detaches the visibility ``V`` unless it softens occlusion for
  differentiation (β = 30, fog) (:func:`detaches_occlusion`);
- **offset penalty**: ``α_t / |P| Σ_j ‖Δ_t^j‖² / ((z1^j)² + 1e-7)``, the squared frame-1 depth of
  the starting position for both offsets (:func:`reference_offset_penalty`);
- **homogeneous offsets**: its δ1 has a fourth, homogeneous component that scales the camera
  translation in frame 2 and is not penalised (:func:`camera_translation_in_reference`; the
  variable ``offset1_w`` of :class:`~weathergen.attack.WeatherVariables`);
- **transparency bound**: θ never exceeds the preset's θ (snow 0.75) (:func:`reference_transparency_bound`);
- **figures**: the adversarial AEE is measured on the float frames of the best step and against
  the random weather's flow whenever a step beats step 0 (:func:`reference_figure_flows`).
"""

from __future__ import annotations

import torch

from ..engine import BETA_ATTACK, CombinedPreset
from .settings import COMPAT_MODES, AttackSettings, transparency_bound

#: Added to the squared depth in the research code's offset penalty.
REFERENCE_DEPTH_EPS = 1e-7

__all__ = ["COMPAT_MODES", "REFERENCE_DEPTH_EPS", "camera_translation_in_reference",
           "detaches_occlusion", "reference_figure_flows", "reference_offset_penalty",
           "reference_transparency_bound", "resets_gradients", "transparency_bound_for"]


def resets_gradients(settings: AttackSettings) -> bool:
    """Whether the gradients are cleared before every step (the paper) or accumulate over the
    steps (the research code)."""
    return settings.compat != "reference"


def detaches_occlusion(settings: AttackSettings) -> bool:
    """Whether the visibility ``V`` passes no gradient: the research code detaches it unless it
    softens occlusion for differentiation (β = 30); the paper's ``V`` is differentiable."""
    return settings.compat == "reference" and settings.beta != BETA_ATTACK


def reference_transparency_bound(preset) -> float:
    """The research code's θ bound: its rendering multiplies ``(tanh η + 1) / 2`` by the preset's
    transparency scale (the supplement's θ column), so snow never exceeds 0.75 and fog 0.25. A
    preset with constant transparency (e.g. fog as the paper's caption reads it) has no counterpart
    there (its ``--constant_transparency`` is never read); it keeps
    :func:`~weathergen.attack.settings.transparency_bound`, so that its particles do not start on
    the bound."""
    if getattr(preset, "transparency_mode", "depth") == "constant":
        return transparency_bound(preset)
    return float(preset.transparency)


def transparency_bound_for(preset, compat: str) -> float:
    """The θ bound of ``preset`` under ``compat`` (combined weather: the largest of its
    layers')."""
    if isinstance(preset, CombinedPreset):
        return max(transparency_bound_for(layer, compat) for layer in preset.layers)
    return reference_transparency_bound(preset) if compat == "reference" else transparency_bound(preset)


def reference_offset_penalty(delta1, delta2, depth1: torch.Tensor, alpha1: float,
                             alpha2: float) -> torch.Tensor:
    """``α1 / |P| Σ_j ‖Δ1^j‖² / ((z1^j)² + ε) + α2 / |P| Σ_j ‖Δ2^j‖² / ((z1^j)² + ε)``, ε = 1e-7.

    ``delta1``, ``delta2``: the offsets this attack adds (N, 3), or None for a fixed one (no
    term); ``depth1``: (N,) the frame-1 camera depth of the starting positions, unclamped.
    Returns a 0-d tensor.
    """
    n = depth1.shape[0]
    total = depth1.new_zeros(())
    if n == 0:
        return total
    scale = depth1.pow(2) + REFERENCE_DEPTH_EPS
    if delta1 is not None:
        total = total + alpha1 * (delta1.pow(2).sum(-1) / scale).mean()
    if delta2 is not None:
        total = total + alpha2 * (delta2.pow(2).sum(-1) / scale).mean()
    return total


def camera_translation_in_reference(cam1_from_ref: torch.Tensor,
                                    cam2_from_ref: torch.Tensor) -> torch.Tensor:
    """The translation ``t`` of ``cam2_from_cam1`` expressed in the reference frame's axes: the
    research code's frame-2 position ``R (X1 + δ1) + (1 + δ1,w) t + m + δ2`` moves by ``δ1,w t``
    (camera-2 axes), i.e. by ``δ1,w`` times this vector in the record's axes.
    Shape: (4, 4) each -> (3,) float64."""
    c1, c2 = cam1_from_ref.double().cpu(), cam2_from_ref.double().cpu()
    t = (c2 @ torch.linalg.inv(c1))[:3, 3]
    return t @ c2[:3, :3]


def reference_figure_flows(best_step: int, benign: torch.Tensor, initial: torch.Tensor,
                           best: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(f̌, f)`` of the research code's adversarial AEE: the best step's flow on float frames,
    against the random weather's flow (step 0) when a step beat step 0, else step 0 against the
    clean flow. Shape: flows (1, 2, H, W)."""
    if best_step > 0:
        return best, initial
    return initial, benign
