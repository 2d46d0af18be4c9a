"""Checking a dataset tree: every problem of every scene, grouped, and optional geometry figures.

:func:`check_dataset` reads every selected pair and returns one :class:`SceneCheck` per scene:
the pairs that read, every problem found (all missing files of a pair, not only the first; frames
with little valid depth; folders whose images cannot be paired), the figures a reader reports
(KITTI's camera motion) and, on request, how well depth and cameras reproduce the dataset's
ground-truth flow (:mod:`~weathergen.datasets.geometry_check`). The command ``weathergen check``
prints this; nothing here prints or writes.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

from ..errors import WeatherGenError
from .base import ERROR, WARNING, Dataset, PairRef, Problem
from .geometry_check import (GeometryStats, PhotometricStats, flow_errors, photometric_errors,
                             sample_indices, static_mask, summarize, summarize_photometric)

#: The warning of a scene whose depth and cameras do not explain its frames (photometric check).
NOT_EXPLAINED = ("depth and cameras do not explain the frames: frame 2 moved by them looks less like "
                 "frame 1 than frame 2 left in place (check the camera file's pose and axes "
                 "conventions, the intrinsics and the depth scale)")

@dataclass
class PairCheck:
    ref: PairRef
    problems: list = field(default_factory=list)
    #: figures the reader reports for the pair (KITTI: the camera motion), one line each
    notes: list = field(default_factory=list)
    geometry_errors: object = None
    #: without ground-truth flow: :func:`photometric_errors` and the number of frame-1 pixels
    photometric: object = None

    @property
    def readable(self) -> bool:
        return not any(p.severity == ERROR for p in self.problems)


@dataclass
class SceneCheck:
    scene: str
    pairs: list = field(default_factory=list)
    #: problems of the scene as a whole (for example images that cannot be paired)
    problems: list = field(default_factory=list)
    geometry: Optional[GeometryStats] = None
    #: the photometric check of the sampled pairs without ground-truth flow
    photometric: Optional[PhotometricStats] = None
    depth_scale: float = 1.0

    @property
    def faulty(self) -> int:
        return sum(not p.readable for p in self.pairs)

    @property
    def ok(self) -> bool:
        return self.faulty == 0 and not any(p.severity == ERROR for p in self.problems)

    def grouped(self) -> list[tuple[str, str, list[str]]]:
        """``(severity, kind, [where, ...])`` for every kind of problem, errors first."""
        groups: "OrderedDict[tuple[str, str], list[str]]" = OrderedDict()
        every = list(self.problems) + [p for pc in self.pairs for p in pc.problems]
        for p in every:
            places = groups.setdefault((p.severity, p.kind), [])
            if p.where and p.where not in places:
                places.append(p.where)
        ordered = sorted(groups.items(), key=lambda item: item[0][0] != ERROR)
        return [(sev, kind, places) for (sev, kind), places in ordered]


def problem_from_message(message: str, files: dict, severity: str = ERROR) -> Problem:
    """A :class:`Problem` from a one-line error ``"PATH: what"``: the path becomes ``where`` so that
    the same problem in several files is one group."""
    for path in sorted({str(v) for v in files.values()}, key=len, reverse=True):
        if message.startswith(path + ": "):
            return Problem(kind=message[len(path) + 2:], where=path, severity=severity)
    return Problem(kind=message, severity=severity)


def check_pair(dataset: Dataset, ref: PairRef, *, geometry: bool = False) -> PairCheck:
    """Every problem of one pair: all missing files, else what loading it reports."""
    result = PairCheck(ref)
    missing = dataset.missing_files(ref)
    if missing:
        result.problems += missing
        return result
    try:
        pair = dataset.load(ref)
    except WeatherGenError as exc:
        result.problems.append(problem_from_message(str(exc), ref.files))
        return result
    result.problems += dataset.pair_warnings(ref, pair)
    result.notes += dataset.pair_notes(pair)
    if geometry:
        result.geometry_errors = flow_errors(pair, static=static_mask(pair))
        if result.geometry_errors is None:
            h, w = pair.size
            result.photometric = (photometric_errors(pair), h * w)
    return result


def check_dataset(dataset: Dataset, *, geometry: bool = False, geometry_pairs: int = 3
                  ) -> list[SceneCheck]:
    """Check every selected pair; one :class:`SceneCheck` per scene (scenes without pairs that
    have problems of their own included), sorted by scene.

    With ``geometry``, up to ``geometry_pairs`` pairs per scene (spread over it) are compared with
    the ground-truth flow.
    """
    try:
        refs = dataset.pairs()
    except WeatherGenError:
        if not dataset.scene_problems():      # nothing to report scene by scene
            raise
        refs = []
    scenes: dict[str, SceneCheck] = {}
    for scene, problems in dataset.scene_problems().items():
        scenes.setdefault(scene, SceneCheck(scene)).problems.extend(problems)
    by_scene: dict[str, list[PairRef]] = {}
    for ref in refs:
        by_scene.setdefault(ref.id.scene, []).append(ref)
    for scene, scene_refs in by_scene.items():
        sc = scenes.setdefault(scene, SceneCheck(scene))
        sampled = set(sample_indices(len(scene_refs), geometry_pairs)) if geometry else set()
        for i, ref in enumerate(scene_refs):
            sc.pairs.append(check_pair(dataset, ref, geometry=i in sampled))
        if geometry:
            sc.geometry = summarize([pc.geometry_errors for pc in sc.pairs
                                     if pc.geometry_errors is not None])
            photo = [pc.photometric for pc in sc.pairs if pc.photometric is not None]
            sc.photometric = summarize_photometric([r for r, _ in photo], sum(n for _, n in photo))
            photo = sc.photometric
            if photo is not None and photo.judged and not photo.explained:
                sc.problems.append(Problem(NOT_EXPLAINED, severity=WARNING))
            elif photo is not None and photo.still_cameras_moving_frames:
                sc.problems.append(Problem(
                    f"the cameras say the camera hardly moves (median predicted motion "
                    f"{photo.motion_px:.2f} px) while the frames differ (mean grey-level "
                    f"difference {photo.unmoved_error:.3f} with nothing moved): check that the "
                    f"camera file gives each frame its own pose (not the same one for every frame)",
                    severity=WARNING))
    for scene, sc in scenes.items():
        sc.depth_scale = getattr(dataset, "scale_of", lambda s: 1.0)(scene)
    return [scenes[s] for s in sorted(scenes)]


def relative(where: str, root: Path) -> str:
    """``where`` without the dataset root in front (the table's title names the root)."""
    prefix = f"{root}/"
    return where[len(prefix):] if where.startswith(prefix) else where
