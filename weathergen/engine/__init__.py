"""The particle engine: presets, billboard templates, particle sampling and the differentiable renderer."""
