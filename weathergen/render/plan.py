"""The rules that turn a render request into a job: which preset, which settings win, the defaults.

Every rule the command line applies lives here, so a library user gets the same behaviour:

- a preset file replaces the preset name; overrides apply on top of either;
- the published weather of the paper (``particles_from`` a set of the research code's particle
  files) is drawn with the preset given, or the one the set's name says;
- re-rendering stored particles (``particles_from``) takes the preset they were sampled from,
  and only the :data:`~weathergen.engine.APPEARANCE_KEYS` may change (they change how the
  particles look, not where they are: the fields of their
  :class:`~weathergen.engine.RenderSettings` other than the templates);
- the output folder defaults to ``out/<preset>``, the pass to ``<preset>_<input pass>``, the batch
  to 8 pairs on CUDA and 1 elsewhere.
"""

from __future__ import annotations

import os

from pathlib import Path
from typing import Mapping, NamedTuple, Optional

import torch

from ..engine import (APPEARANCE_KEYS, CombinedPreset, FieldPreset, Preset, RenderSettings,
                      list_presets, load_preset)
from ..engine.weather.presets import UNSCALED
from ..errors import ConfigError
from ..io.published_weather import is_published_set
from ..outputs import read_manifest

class ResolvedPreset(NamedTuple):
    """The preset of a run, its name, and (re-rendering) the particle settings that change."""

    preset: Preset
    name: str
    appearance: dict


#: How the published sets of the paper's weather are named (``<name>_npz``, ``<name>_png``, or
#: ``weather_<tag>`` as the research code's generator writes them), where the name is not the
#: preset's own with ``-`` for ``_``: the preset each was generated with.
PUBLISHED_NAMES = {"color_additive_white": "additive-white", "color_additive_red": "additive-red",
                   "color_additive_green": "additive-green", "color_additive_blue": "additive-blue",
                   "color_additive_color": "additive-color", "color_alpha_white": "alpha-white",
                   "color_alpha_red": "alpha-red", "color_alpha_green": "alpha-green",
                   "color_alpha_blue": "alpha-blue", "color_alpha_color": "alpha-color",
                   "rain_1500": "motion-blur-0.15"}


def published_preset(folder: str | Path) -> Optional[str]:
    """The bundled preset a published set of the paper's weather was generated with, from the
    set's folder name (``particles_3000_npz`` -> ``particles-3000``, ``color_additive_red_npz``
    -> ``additive-red``, ``weather_snow`` -> ``snow``), or None where the name does not say."""
    name = Path(folder).resolve().name
    for suffix in ("_npz", "_png"):
        name = name.removesuffix(suffix)
    name = name.removeprefix("weather_")
    candidate = PUBLISHED_NAMES.get(name, name.replace("_", "-"))
    return candidate if candidate in list_presets("paper") else None


def resolve_preset(preset: Optional[str] = None, preset_file: Optional[str | Path] = None,
                   overrides: Optional[Mapping[str, str]] = None,
                   particles_from: Optional[str | Path] = None) -> ResolvedPreset:
    """The preset of a run and, when re-rendering, the particle settings that change.

    ``preset`` names a bundled preset (default ``snow``); ``preset_file`` (a TOML file) replaces
    it; ``overrides`` map preset keys to values (as :func:`~weathergen.engine.load_preset` takes
    them). With ``particles_from`` (the folder of an earlier render or attack) the stored preset
    is used and ``preset``/``preset_file`` are ignored; overrides of keys other than
    :data:`APPEARANCE_KEYS` raise ConfigError. A combined preset (``rain-heavy+fog-light``, layer
    overrides as ``LAYER.KEY``) is named by its layers; its stored particles re-render without
    overrides. ``particles_from`` a published set of the paper's weather
    (:func:`~weathergen.io.published_weather.is_published_set`): its files fix the particles,
    the preset (given, or the one the set's name says, :func:`published_preset`) says how they
    are drawn, with any overrides.
    """
    overrides = dict(overrides or {})
    if particles_from is not None and is_published_set(particles_from):
        return _published(preset, preset_file, overrides, particles_from)
    preset = preset or "snow"
    if particles_from is None:
        resolved = load_preset(preset_file or preset, overrides)
        if isinstance(resolved, CombinedPreset):
            return ResolvedPreset(resolved, resolved.name, {})
        return ResolvedPreset(resolved, Path(preset_file).stem if preset_file else preset, {})
    # Re-rendering: the sampled particles fix everything but their appearance settings.
    stored = read_manifest(particles_from, "particles_from")
    fixed = sorted(k for k in overrides if k not in APPEARANCE_KEYS)
    if fixed:
        raise ConfigError(f"${{overrides}} {', '.join(fixed)}: fixed by the stored particles; only "
                          f"{', '.join(APPEARANCE_KEYS)} can change when re-rendering")
    if stored.preset.get("model") == CombinedPreset.model:
        if overrides:    # a layer's settings are its own; re-render it alone to change them
            raise ConfigError(f"${{overrides}} {', '.join(sorted(overrides))}: the stored "
                              f"particles are of the combined preset {stored.preset_name}, "
                              f"whose layers re-render as stored (no overrides)")
        return ResolvedPreset(CombinedPreset.from_dict(stored.preset), stored.preset_name, {})
    values = {k: v for k, v in stored.preset.items() if k not in ("name", "source")}
    if "model" not in values:    # a paper preset: one recorded before frame scaling used it as given
        values = {**UNSCALED, **values}
    name = stored.preset_name
    model = values.get("model", "paper")                 # every key is set anyway: any preset
    base = name if name in list_presets(model) else list_presets(model)[0]   # of its model
    resolved = load_preset(base, {**values, **overrides})
    if not overrides:
        appearance = {}
    elif isinstance(resolved, FieldPreset):   # its streak follows the dataset's frame rate
        appearance = {"blend": resolved.blend, "blur_samples": resolved.blur_samples,
                      "coarse": resolved.coarse}
    else:
        appearance = RenderSettings.from_preset(resolved).appearance()
    return ResolvedPreset(resolved, name, appearance)


def _published(preset, preset_file, overrides, folder) -> ResolvedPreset:
    """The preset a published set is drawn with: given, or named by the set's folder."""
    name = Path(preset_file).stem if preset_file else preset or published_preset(folder)
    if name is None:
        raise ConfigError(f"${{particles_from}} {folder}: published weather does not record the "
                          f"preset it was generated with, and the folder's name does not say: "
                          f"name it with ${{preset}} (e.g. particles-3000, motion-blur-0.15, "
                          f"additive-red, size-fog)")
    resolved = load_preset(preset_file or name, overrides)
    if not isinstance(resolved, Preset):
        raise ConfigError(f"${{preset}} {name}: published weather is drawn with a preset of the "
                          f"paper's model (the research code's), not a {resolved.model} preset")
    return ResolvedPreset(resolved, name, {})


def default_out(label: str) -> Path:
    """Where a run writes when no folder is given: ``out/<label>``."""
    return Path("out") / label


def default_pass_name(preset_name: str, input_pass: str) -> str:
    """The output pass of a render: ``<preset>_<input pass>``, e.g. ``snow_clean``."""
    return f"{preset_name}_{input_pass}"


def default_batch_size(device: str | torch.device) -> int:
    """Pairs rendered together when none is given: 8 on CUDA (worth it there), 1 elsewhere."""
    return 8 if torch.device(device).type == "cuda" else 1


#: The fewest pairs worth starting a worker process for: a worker imports torch (seconds) and holds
#: about 300 MB; a pair takes a fraction of a second to a few seconds on one CPU thread.
PAIRS_PER_WORKER = 8


def auto_workers(pairs: int, device: str = "cpu", cores: Optional[int] = None) -> int:
    """The worker count of ``workers=auto`` (``RenderJob.workers = 0``).

    Every pair renders on one CPU thread (so that the bytes do not depend on the machine), so on
    a CPU the cores are used by rendering pairs side by side: one worker per core, but no more
    than one per :data:`PAIRS_PER_WORKER` pairs, since starting a worker costs more than a few
    pairs take. On a GPU one process feeds the device (it batches pairs instead).
    """
    if not str(device).startswith("cpu"):
        return 1
    if cores is None:       # the cores this process may run on (its affinity mask where it has one)
        cores = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                 else os.cpu_count() or 1)
    return max(1, min(cores, pairs // PAIRS_PER_WORKER))
