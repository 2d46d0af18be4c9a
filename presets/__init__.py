"""Preset files; installed as ``weathergen.presets`` so the package finds them after ``pip install .``."""
