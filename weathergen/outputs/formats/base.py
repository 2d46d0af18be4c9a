"""What a frame format of an output is: how a weather frame is written and read back."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np


@dataclass(frozen=True)
class FrameFormat:
    """One format of an output's weather frames (``render --format NAME``).

    Attributes:
        name: what ``--format`` takes and the manifest records.
        extension: the files' extension.
        folder_suffix: added to the pass folder's name (``snow_clean`` + ``_exr``), so that the
            formats of one output sit side by side.
        write: ``write(path, rgb, opacity) -> path``, atomically. Shape: rgb (H, W, 3) float in
            [0, 1]; opacity (H, W) float (a format that holds no opacity ignores it).
        read: ``read(path) -> rgb``. Shape: (H, W, 3) float32 in [0, 1].
        size: ``size(path) -> (height, width)`` of a frame.
        read_opacity: ``read_opacity(path) -> (H, W) float32``, the particles' opacity the file
            holds beside the colour; None for a format that holds none.
    """

    name: str
    extension: str
    folder_suffix: str
    write: Callable[[Path, np.ndarray, np.ndarray], Path]
    read: Callable[[Path], np.ndarray]
    size: Callable[[Path], tuple[int, int]]
    read_opacity: Optional[Callable[[Path], np.ndarray]] = None
