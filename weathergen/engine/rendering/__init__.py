"""Particle records and cameras in, weather frames out, differentiably.

The render core's stages, in order: :mod:`.tracks` (what every view draws), :mod:`.stamps`
(templates rotated and scaled), :mod:`.splat` (stamps summed per pixel; :mod:`.ragged` lays out
the runs, :mod:`.coarse` draws large billboards coarse), :mod:`.planes` and :mod:`.composite`
(sums to frames, every blend mode). Around the core: :mod:`.transmittance` (seeing the scene and
the particles through the atmosphere), :mod:`.combined` (a combined preset's layers in one pass),
:mod:`.renderer` (the public entry points), :mod:`.stereo` (a second camera) and
:mod:`.groundtruth` (the particle layer's flow and opacity)."""
