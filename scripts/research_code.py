"""The paper's research code, opened on a Sintel-format tree, for the comparison scripts.

Imports nothing of weathergen, so that it runs in the research code's own interpreter too.
"""

from __future__ import annotations

import sys
import types
from argparse import Namespace
from pathlib import Path

import numpy as np


def research_sintel(research: Path, tree: Path):
    """The research code's Sintel reader on ``tree`` (its training split, clean pass), with the
    code at ``research`` importable. Its ``readFlow`` is replaced (it fails under numpy 2; the
    flow is not used) and torchvision, which it imports but these scripts never need, stubbed."""
    sys.path.insert(0, str(research))
    sys.modules.setdefault("torchvision", types.ModuleType("torchvision"))
    from helper_functions import datasets, frame_utils

    def read_flo(path):
        with open(path, "rb") as f:
            np.fromfile(f, np.float32, 1)
            w, h = np.fromfile(f, np.int32, 2)
            return np.fromfile(f, np.float32, 2 * int(w) * int(h)).reshape(int(h), int(w), 2)

    frame_utils.readFlow = read_flo
    data_args = Namespace(dstype="clean", single_scene="", from_scene="", frame_per_scene=0,
                          from_frame=0, scene_scale=1.0, weather_data="")
    return datasets.MpiSintel(data_args, split="training", root=str(tree), has_gt=True,
                              get_weather=True)
