"""Video previews of a render output, made to be watched.

A ``--sequence`` output plays each scene's frames in order, scene after scene, at the dataset's
frame rate (its reader's ``frame_rate``, for the input the manifest records), or a field preset's
own ``frame_rate`` when it sets one. An output of pairs shows each pair's frame 1 and frame 2
alternating at a calm :data:`PAIR_FPS` (each frame half a second), ``cycles`` times (by default
for :data:`PAIR_SECONDS` per pair), pair after pair, so that the particles' frame-to-frame motion
is seen as a flow network sees it, without a strobe. A video shorter than :data:`MIN_SECONDS`
(a sequence of a few frames) is played again until it lasts that long. Beside each weather frame
the clean input frame and the particles' opacity may be shown (input | weather | opacity, as on
the contact sheet).

:func:`video_preview` plans the video (which frames, how large, how fast) without reading any
image; :meth:`VideoPreview.frames` reads, composes and yields them one at a time, so memory does
not grow with the output's length; :func:`weathergen.io.video.write_video` writes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np
import torch

from ..datasets import Dataset, frame_rate_of, reopen_dataset
from ..engine import load_particles, render_pair
from ..errors import ConfigError, DatasetError
from ..framepair import FramePair, PairId
from ..outputs import OutputManifest, PairOutput, WeatherFolder, read_manifest
from .preview import caption_tile, check_tile_width


#: The shortest video a preview writes, in seconds: shorter ones are played again until this long.
MIN_SECONDS = 2.0
#: Frames per second of an output of pairs: frame 1 and frame 2 each held half a second.
PAIR_FPS = 2.0
#: How long each pair plays by default (frame 1 / frame 2 alternating), in seconds.
PAIR_SECONDS = 2.0
#: The frame rates a video may be given, frames per second.
MIN_FPS, MAX_FPS = 0.1, 240.0
#: The most cycles (frame 1, frame 2) of each pair a video of pairs may be given.
MAX_CYCLES = 100


def output_frame_rate(manifest: OutputManifest) -> float:
    """Frames per second of an output's input: a field preset's ``frame_rate`` when it sets one,
    else the dataset's (:func:`~weathergen.datasets.frame_rate_of`; 30 for an unknown one)."""
    preset = manifest.preset or {}          # an Lp attack has none
    if preset.get("model") == "field" and float(preset.get("frame_rate") or 0) > 0:
        return float(preset["frame_rate"])
    return frame_rate_of(manifest.input.get("dataset", ""))


@dataclass(frozen=True)
class Shot:
    """One frame of the video: frame 1 (``second`` False) or frame 2 of a pair."""

    pair: PairId
    second: bool = False

    @property
    def frame(self) -> int:
        """The frame's number in its scene (as in the file names)."""
        return self.pair.frame + int(self.second)


@dataclass
class VideoPreview:
    """A planned video of a render output (see the module doc).

    ``shots`` lists the video's frames in order, played ``loops`` times; every frame is ``size``
    (width, height) pixels: one tile per shown column (input, weather, opacity) of ``tile``
    (width, height).
    """

    folder: Path
    manifest: OutputManifest
    shots: list[Shot]
    fps: float
    tile: tuple[int, int]
    with_input: bool = False
    with_opacity: bool = False
    captions: bool = True
    sequence: bool = False
    pairs: int = 0                                 # pairs shown
    total: int = 0                                 # complete pairs in the output
    loops: int = 1                                 # how often ``shots`` play (MIN_SECONDS)
    unreadable: list = field(default_factory=list) # pairs left out: their particle file's problem
    _input: Optional[tuple[Dataset, dict]] = field(default=None, repr=False)   # opened on first use

    @property
    def columns(self) -> int:
        return 1 + int(self.with_input) + int(self.with_opacity)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of a video frame."""
        return self.tile[0] * self.columns, self.tile[1]

    @property
    def count(self) -> int:
        """Frames in the video (``shots`` times ``loops``)."""
        return len(self.shots) * self.loops

    @property
    def seconds(self) -> float:
        return self.count / self.fps

    def frames(self, progress: Optional[Callable[[int, int], None]] = None) -> Iterator[np.ndarray]:
        """The video's frames in order. Shape: each (H, W, 3) uint8 RGB, ``size`` pixels.

        ``progress(done, count)`` is called after each frame is taken. A looped video (a short
        one) composes its frames once and plays them ``loops`` times."""
        kept: list[np.ndarray] = []
        cached: Optional[tuple[PairId, dict]] = None
        done = 0
        for loop in range(self.loops):
            for i, shot in enumerate(self.shots):
                if loop:
                    frame = kept[i]
                else:
                    if cached is None or cached[0] != shot.pair:
                        cached = (shot.pair, self._pair_tiles(shot.pair))
                    frame = cached[1][shot.second]
                    if self.loops > 1:
                        kept.append(frame)
                yield frame
                done += 1
                if progress is not None:
                    progress(done, self.count)

    def _pair_tiles(self, pair_id: PairId) -> dict[bool, np.ndarray]:
        """The composed video frames of one pair that the video shows (frame 1 under False,
        frame 2 under True)."""
        m = self.manifest
        out = PairOutput.of(self.folder, pair_id, m.pass_name, m.fmt, sequence=self.sequence)
        shown = sorted({s.second for s in self.shots if s.pair == pair_id})
        stored = {s: out.stored_opacity(int(s)) for s in shown} if self.with_opacity else {}
        pair = None
        if self.with_input or (self.with_opacity and None in stored.values()):
            pair = self._dataset_pair(pair_id)
        opacity = {}
        if stored and None not in stored.values():  # the format stores it beside the colour
            opacity = stored
        elif self.with_opacity:               # re-rendered from the stored particles (exact)
            with torch.no_grad():
                rendered = render_pair(pair, load_particles(out.metadata))
            opacity = {False: rendered.opacity1[0, 0].numpy(), True: rendered.opacity2[0, 0].numpy()}
        preset = str(m.preset_name)
        tiles = {}
        for second in shown:
            label = f"{pair_id.scene} {pair_id.frame + int(second)}" if self.captions else ""
            row = []
            if self.with_input:
                clean = (pair.image2 if second else pair.image1).permute(1, 2, 0).numpy()
                row.append(caption_tile(clean, self.tile, label))
            weather = out.read_frame(int(second))
            text = (preset if self.with_input else f"{label}  {preset}") if self.captions else ""
            row.append(caption_tile(weather, self.tile, text))
            if self.with_opacity:
                alpha = np.clip(opacity[second], 0, 1)
                row.append(caption_tile(np.repeat(alpha[..., None], 3, 2), self.tile,
                                        "opacity" if self.captions else ""))
            tiles[second] = np.hstack(row)
        return tiles

    def _dataset_pair(self, pair_id: PairId) -> FramePair:
        """The clean pair from the input the manifest records (opened on first use)."""
        if self._input is None:
            ds = reopen_dataset(self.manifest.input)
            self._input = (ds, {ref.id: ref for ref in ds.pairs()})
        ds, refs = self._input
        if pair_id not in refs:
            raise DatasetError(f"{self.manifest.input.get('root')}: the recorded input has no pair "
                               f"{pair_id} (moved or changed since the render?)")
        return ds.load(refs[pair_id])


def video_preview(render_dir: str | Path, *, pairs: Optional[int] = None,
                  cycles: Optional[int] = None, fps: Optional[float] = None,
                  with_input: bool = False, with_opacity: bool = False,
                  width: Optional[int] = None, captions: bool = True) -> VideoPreview:
    """Plan the video of a render output (see the module doc).

    ``pairs``: only the first complete pairs (default all); ``cycles``: how often an output of
    pairs shows frame 1 and frame 2 of each pair (default: for ``PAIR_SECONDS``,
    ``ceil(PAIR_SECONDS * fps / 2)``; at most ``MAX_CYCLES``; a ``--sequence`` output plays each
    frame once and refuses it); ``fps``: the frame rate, within [``MIN_FPS``, ``MAX_FPS``]
    (default: a sequence's dataset rate, :func:`output_frame_rate`; ``PAIR_FPS`` for pairs);
    ``width``: of each tile, in pixels, within [``MIN_TILE_WIDTH``, ``MAX_TILE_WIDTH``] of
    :mod:`.preview` (default the frames' own);
    ``with_input`` / ``with_opacity``: show the clean input frame and the particles' opacity
    beside the weather frame; ``captions``: scene, frame and preset on the tiles. A video shorter
    than ``MIN_SECONDS`` plays its frames again (``loops``) until it lasts that long.

    Raises ConfigError for a folder that is not a render output or a bad option (named), and
    DatasetError when it holds no complete pair.
    """
    _check_options(pairs, width, fps, cycles)          # before any file is read
    render_dir = Path(render_dir)
    manifest = read_manifest(render_dir, "preview")
    if with_opacity and not manifest.holds_particles:
        raise ConfigError(f"${{with_opacity}}: {render_dir} holds no particles to show (an Lp "
                          f"attack, {manifest.preset_name}, perturbs the frames themselves)")
    sequence = manifest.sequence
    if fps is not None:
        rate = float(fps)
    else:
        rate = output_frame_rate(manifest) if sequence else PAIR_FPS
    if sequence and cycles is not None:
        raise ConfigError("${cycles} applies to outputs of pairs; a --sequence output plays its "
                          "frames in order")
    folder = WeatherFolder.open(render_dir, skip_unreadable=True)
    complete = folder.pairs
    chosen = complete if pairs is None else complete[:pairs]
    shots: list[Shot] = []
    if sequence:
        starts = {(p.scene, p.frame) for p in chosen}
        for p in chosen:
            shots.append(Shot(p))
            out = PairOutput.of(render_dir, p, manifest.pass_name, manifest.fmt, sequence=True)
            if (p.scene, p.frame + 1) not in starts and out.frame_file(1) in out.listed_files():
                shots.append(Shot(p, True))     # the last pair of a scene wrote its second frame
    else:
        repeat = cycles if cycles is not None else max(1, math.ceil(PAIR_SECONDS * rate / 2 - 1e-9))
        for p in chosen:
            shots += [Shot(p), Shot(p, True)] * repeat
    loops = max(1, math.ceil(MIN_SECONDS * rate / len(shots) - 1e-9))
    first = PairOutput.of(render_dir, chosen[0], manifest.pass_name, manifest.fmt,
                          sequence=sequence)
    h, w = first.frame_size()
    tile = (w, h) if width is None else (int(width), max(1, round(h * width / w)))
    return VideoPreview(render_dir, manifest, shots, rate, tile, with_input, with_opacity,
                        captions, sequence, len(chosen), len(complete), loops=loops,
                        unreadable=folder.unreadable)


def _check_options(pairs: Optional[int], width: Optional[int], fps: Optional[float],
                   cycles: Optional[int]) -> None:
    """ConfigError for an option of :func:`video_preview` out of its range (NaN included)."""
    if pairs is not None and pairs < 1:
        raise ConfigError(f"${{pairs}} {pairs}: must be >= 1")
    if width is not None:
        check_tile_width(width)
    if fps is not None and not MIN_FPS <= fps <= MAX_FPS:
        raise ConfigError(f"${{fps}} {fps!r}: must be in [{MIN_FPS:g}, {MAX_FPS:g}] frames per "
                          "second")
    if cycles is not None and not 1 <= cycles <= MAX_CYCLES:
        raise ConfigError(f"${{cycles}} {cycles}: must be in [1, {MAX_CYCLES}]")
