"""The particle engine: presets, billboard templates, particle sampling and the differentiable renderer.

Typical use (any preset: the paper's, a weather field, an atmosphere alone, a combination)::

    from weathergen.engine import Weather, render_pair
    weather = Weather("snow", seed=0, overrides={"count": "500"})
    out = weather.render(pair)                  # out.image1, out.image2, out.opacity1, out.opacity2
    particles = weather.sample(pair)            # the record: save, optimise, render_pair(pair, particles)

Its subpackages, in the order the data flows: :mod:`.weather` (presets, templates, the
atmosphere model), :mod:`.records` (the particle records), :mod:`.sampling` (a pair's particles
from a preset) and :mod:`.rendering` (records and cameras -> frames). The renderer module is
``rendering.renderer`` (not ``render``) so that it never shadows the :func:`render` function.
"""

from __future__ import annotations

from .sampling.field import (Field, field_for_pair, field_pair_particles, field_record,
                             frame_particles, make_field, pair_trajectories, pair_views,
                             sample_field_particles, sample_layers, sample_weather, scene_seed)
from .pipeline import Weather
from .rendering.groundtruth import ParticleTruth, particle_truth, seen_flow
from .records.layered import LayeredParticles, layer_seed, load_particles
from .records.particles import Particles, empty_particles, from_atanh, to_atanh
from .weather.optics import FieldOptics
from .weather.presets import (EXAMPLE_COMBINATIONS, REFERENCE_FRAME, CombinedPreset, FieldPreset,
                              FrameScaling, Preset, frame_scaling, list_presets, load_preset,
                              parse_override, parse_set_options, preset_keys)
from .rendering.renderer import (BETA_ATTACK, BETA_RENDER, RenderOutput, StampSet, build_stamps,
                                 render, render_pair, render_view)
from .common import reference_transforms, resolve_device
from .sampling.pair import sample_particles, visible_counts, world_down
from .records.settings import APPEARANCE_KEYS, RenderSettings
from .weather.templates import (TemplateLibrary, generate_templates, load_templates,
                                write_builtin_templates)
from .views import View

__all__ = ["APPEARANCE_KEYS", "BETA_ATTACK", "BETA_RENDER", "CombinedPreset",
           "EXAMPLE_COMBINATIONS", "Field", "FieldOptics", "FieldPreset", "FrameScaling",
           "LayeredParticles", "ParticleTruth", "Particles", "Preset", "REFERENCE_FRAME", "RenderOutput",
           "RenderSettings", "StampSet", "TemplateLibrary", "View", "Weather", "build_stamps",
           "empty_particles", "frame_particles", "frame_scaling", "from_atanh", "generate_templates",
           "layer_seed", "list_presets", "load_particles", "load_preset", "load_templates", "make_field",
           "field_pair_particles", "field_for_pair", "field_record", "pair_trajectories",
           "pair_views",
           "parse_override", "parse_set_options", "particle_truth", "preset_keys",
           "reference_transforms", "render", "render_pair", "render_view", "resolve_device",
           "sample_field_particles", "sample_layers", "sample_particles", "sample_weather", "scene_seed",
           "seen_flow", "to_atanh", "visible_counts", "world_down", "write_builtin_templates"]
