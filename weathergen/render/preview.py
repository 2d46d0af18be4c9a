"""Contact sheets of a render output: original and weather frames side by side with the opacity."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from ..datasets import reopen_dataset
from ..engine import load_particles, render_pair
from ..errors import ConfigError, FormatError, WeatherGenError
from ..io.images import to_uint8
from ..outputs import PairOutput, read_manifest
from ..words import counted


#: The narrowest and widest tile a preview draws, pixels: three tiles side by side stay within
#: what MPEG-4 encodes (8191 pixels a side).
MIN_TILE_WIDTH, MAX_TILE_WIDTH = 16, 2048


def check_tile_width(width: int) -> None:
    """ConfigError unless ``width`` is within [MIN_TILE_WIDTH, MAX_TILE_WIDTH]."""
    if not MIN_TILE_WIDTH <= width <= MAX_TILE_WIDTH:
        raise ConfigError(f"${{width}} {width}: must be in [{MIN_TILE_WIDTH}, {MAX_TILE_WIDTH}] "
                          "pixels")


def caption_tile(img: np.ndarray, size: tuple[int, int], text: str) -> np.ndarray:
    """Resize a float [0, 1] image to ``size`` (w, h), as uint8 with a caption (none for "")."""
    out = to_uint8(cv2.resize(img, size, interpolation=cv2.INTER_AREA))
    if not text:
        return out
    # A dark outline: the caption itself shifted by one pixel each way (a thicker stroke would
    # advance wider per character and drift away from the white text).
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            if dx or dy:
                cv2.putText(out, text, (6 + dx, 18 + dy), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                            (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(out, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return out


@dataclass
class ContactSheet:
    """A contact sheet and what it shows: ``shown`` of the ``total`` complete pairs;
    ``unreadable``: one line per pair left out because its particle file cannot be read."""

    image: np.ndarray           # (rows * h [+ footer], 3 * width, 3) uint8 RGB
    shown: int
    total: int
    unreadable: list = field(default_factory=list)

    @property
    def partial(self) -> bool:
        return self.shown < self.total


def contact_sheet(render_dir: str | Path, pairs: int = 4, width: int = 480) -> ContactSheet:
    """One row per pair: original frame 1 | weather frame 1 | particle opacity of frame 1.

    The first ``pairs`` complete pairs are shown; when the output holds more, a footer below the
    rows says how many of how many the sheet shows. The input frames are read through the dataset
    recorded in the manifest; the opacity is re-rendered from the stored particle metadata (exact,
    whatever the output format), and is empty for an Lp attack's output, which stores no
    particles.
    """
    check_tile_width(width)
    render_dir = Path(render_dir)
    manifest = read_manifest(render_dir, "preview")
    ds = reopen_dataset(manifest.input)
    rows = []
    total = 0
    unreadable = []
    for ref in ds.pairs():
        out = PairOutput.of(render_dir, ref.id, manifest.pass_name, manifest.fmt, manifest.geometry,
                            sequence=manifest.sequence)
        if not out.is_complete():
            problem = out.unreadable()
            if problem is not None:
                unreadable.append(f"{problem}; pair {ref.id} is left out")
            continue
        total += 1
        if len(rows) == pairs:
            continue            # only counted
        pair = ds.load(ref)
        if manifest.holds_particles:
            try:
                particles = load_particles(out.metadata)
            except FormatError as exc:
                unreadable.append(f"{exc}; pair {ref.id} is left out")
                total -= 1
                continue
            with torch.no_grad():
                opacity = render_pair(pair, particles).opacity1[0, 0]
            opacity = opacity.clamp(0, 1).numpy()
        else:                   # an Lp attack: the frames themselves are perturbed
            opacity = np.zeros(pair.image1.shape[-2:], np.float32)
        weather = out.read_frame(0)
        original = pair.image1.permute(1, 2, 0).numpy()
        h, w = original.shape[:2]
        size = (width, max(1, round(h * width / w)))
        tiles = [caption_tile(original, size, f"{ref.id.scene} {ref.id.frame}"),
                 caption_tile(weather, size, manifest.data.get("preset_name", "")),
                 caption_tile(np.repeat(opacity[..., None], 3, 2), size,
                              "opacity" if manifest.holds_particles else "no particles")]
        rows.append(np.hstack(tiles))
    if not rows:
        why = f" ({len(unreadable)} with unreadable particle files: {unreadable[0]})" if unreadable else ""
        raise WeatherGenError(f"{render_dir}: no complete pair to preview{why}")
    if len(rows) < total:
        footer = np.full((28, rows[0].shape[1], 3), 32, np.uint8)
        cv2.putText(footer, f"{len(rows)} of {counted(total, 'pair')} shown (--pairs {total} shows all)", (6, 19),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(footer)
    return ContactSheet(np.vstack(rows), min(pairs, total), total, unreadable)
