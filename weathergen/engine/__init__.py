"""The particle engine: presets, billboard templates, particle sampling and the differentiable renderer.

Typical use::

    from weathergen.engine import load_preset, sample_particles, render_pair
    preset = load_preset("snow", overrides={"count": "500"})
    particles = sample_particles(pair, preset, seed=0)
    out = render_pair(pair, particles)          # out.image1, out.image2, out.opacity1, out.opacity2

The renderer module is ``renderer`` (not ``render``) so that it never shadows the :func:`render`
function.
"""

from __future__ import annotations

from .field import (Field, field_for_pair, field_record, frame_particles, make_field,
                    pair_particles, pair_trajectories, pair_views, sample_field_particles,
                    sample_layers, sample_weather, scene_seed)
from .groundtruth import ParticleTruth, particle_truth, seen_flow
from .layers import LayeredParticles, layer_seed, load_particles
from .particles import Particles, empty_particles, from_atanh, to_atanh
from .optics import FieldOptics
from .presets import (EXAMPLE_COMBINATIONS, REFERENCE_FRAME, CombinedPreset, FieldPreset,
                      FrameScaling, Preset, frame_scaling, list_presets, load_preset, parse_override,
                      parse_set_options, preset_keys)
from .renderer import (BETA_ATTACK, BETA_RENDER, RenderOutput, StampSet, build_stamps, render,
                       render_pair, render_view)
from .sampling import (reference_transforms, resolve_device, sample_particles, visible_counts,
                       world_down)
from .settings import APPEARANCE_KEYS, RenderSettings
from .templates import (TemplateLibrary, generate_templates, load_templates,
                        write_builtin_templates)
from .tracks import View

__all__ = ["APPEARANCE_KEYS", "BETA_ATTACK", "BETA_RENDER", "CombinedPreset",
           "EXAMPLE_COMBINATIONS", "Field", "FieldOptics", "FieldPreset", "FrameScaling",
           "LayeredParticles", "ParticleTruth", "Particles", "Preset", "REFERENCE_FRAME", "RenderOutput",
           "RenderSettings", "StampSet", "TemplateLibrary", "View", "build_stamps",
           "empty_particles", "frame_particles", "frame_scaling", "from_atanh", "generate_templates",
           "layer_seed", "list_presets", "load_particles", "load_preset", "load_templates", "make_field",
           "pair_particles", "field_for_pair", "field_record", "pair_trajectories", "pair_views",
           "parse_override", "parse_set_options", "particle_truth", "preset_keys",
           "reference_transforms", "render", "render_pair", "render_view", "resolve_device",
           "sample_field_particles", "sample_layers", "sample_particles", "sample_weather", "scene_seed",
           "seen_flow", "to_atanh", "visible_counts", "world_down", "write_builtin_templates"]
