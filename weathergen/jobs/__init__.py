"""What the render and attack jobs share, so that neither job imports the other.

- :mod:`.particles`: which particles a pair gets (its own seed, or an earlier output's), the
  same rule for ``render`` and ``attack``;
- :mod:`.visibility`: the particle centres a pair's frames show, ``few_in_frame2`` and the run's
  note about such pairs, and its note about pairs of mostly estimated depth;
- :mod:`.threads`: the torch threads a job uses, restored when it ends.
"""

from __future__ import annotations

from .particles import (layer_seeds, pair_particles, pair_seed, scene_airlight, scene_firsts, scene_key,
                        selected_pairs, weather_scaling, weather_seed)
from .threads import torch_threads
from .visibility import FRAME2_KEPT_MIN, depth_note, few_in_frame2, frame2_note, visibility_of

__all__ = ["FRAME2_KEPT_MIN", "depth_note", "few_in_frame2", "frame2_note", "layer_seeds",
           "pair_particles", "pair_seed", "scene_airlight", "scene_firsts", "scene_key",
           "selected_pairs", "torch_threads",
           "visibility_of", "weather_scaling", "weather_seed"]
