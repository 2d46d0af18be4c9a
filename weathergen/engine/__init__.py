"""The particle engine: presets, billboard templates, particle sampling and the differentiable renderer.

Typical use::

    from weathergen.engine import load_preset, sample_particles, render_pair
    preset = load_preset("snow", overrides={"count": "500"})
    particles = sample_particles(pair, preset, seed=0)
    out = render_pair(pair, particles)          # out.image1, out.image2, out.opacity1, out.opacity2

Names are imported lazily so that ``import weathergen.engine`` stays cheap. The renderer module
is ``renderer`` (not ``render``) so that it never shadows the :func:`render` function.
"""

from __future__ import annotations

import importlib

_EXPORTS = {
    "Preset": "presets", "load_preset": "presets", "list_presets": "presets",
    "parse_override": "presets", "parse_set_options": "presets", "preset_keys": "presets",
    "TemplateLibrary": "templates", "load_templates": "templates",
    "generate_templates": "templates", "write_builtin_templates": "templates",
    "Particles": "particles", "empty_particles": "particles", "to_atanh": "particles",
    "from_atanh": "particles",
    "sample_particles": "sampling", "reference_transforms": "sampling", "world_down": "sampling",
    "resolve_device": "sampling",
    "render": "renderer", "render_pair": "renderer", "build_stamps": "renderer",
    "RenderOutput": "renderer", "StampSet": "renderer", "BETA_RENDER": "renderer",
    "BETA_ATTACK": "renderer",
    "FieldPreset": "field_presets", "DATASET_FRAME_RATES": "field_presets",
    "Field": "field", "make_field": "field", "sample_field_particles": "field",
    "scene_seed": "field", "sample_weather": "field", "frame_particles": "field",
    "pair_particles": "field", "FieldOptics": "particles", "View": "perframe",
    "render_view": "perframe", "particle_truth": "groundtruth", "seen_flow": "groundtruth",
    "ParticleTruth": "groundtruth",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'weathergen.engine' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return __all__
