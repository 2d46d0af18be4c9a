"""What every dataset reader shares: the selection of frame pairs, pair references, checking.

A reader lists its frame pairs cheaply (:meth:`Dataset.pairs`, file names only) and reads one on
demand (:meth:`Dataset.load`), returning the :class:`~weathergen.framepair.FramePair` record. Readers
never write files.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional

from ..errors import ConfigError, DatasetError, WeatherGenError
from ..framepair import FramePair, PairId
from ..words import plural


@dataclass(frozen=True)
class Selection:
    """Which frame pairs of a dataset to use (shared by every command that reads data).

    ``frames_per_scene`` counts pairs; ``first_frame`` is a frame number as in the file names.
    The paper's "Sintel-tr115" is ``Selection(split="training", frames_per_scene=5)``.
    """

    split: str = "training"
    pass_: str = "clean"
    scenes: Optional[tuple[str, ...]] = None
    from_scene: Optional[str] = None
    frames_per_scene: Optional[int] = None
    first_frame: Optional[int] = None

    def __post_init__(self):
        if self.frames_per_scene is not None and self.frames_per_scene < 1:
            raise ConfigError(f"frames per scene must be at least 1, got {self.frames_per_scene}")
        if self.first_frame is not None and self.first_frame < 0:
            raise ConfigError(f"first frame must not be negative, got {self.first_frame}")

    def narrowing(self) -> list[str]:
        """The options that narrow this selection, as ``"${option} value"`` for messages."""
        out = []
        if self.scenes:
            out.append(f"${{scenes}} {','.join(self.scenes)}")
        if self.from_scene is not None:
            out.append(f"${{from_scene}} {self.from_scene}")
        if self.first_frame is not None:
            out.append(f"${{first_frame}} {self.first_frame}")
        if self.frames_per_scene is not None:
            out.append(f"${{frames_per_scene}} {self.frames_per_scene}")
        return out

    def pick_scenes(self, available: list[str], where: Path) -> list[str]:
        """Apply ``scenes`` and ``from_scene`` to the sorted list of scenes found at ``where``."""
        chosen = list(available)
        if self.scenes:
            unknown = [s for s in self.scenes if s not in available]
            if unknown:
                raise ConfigError(f"{where}: no scene named {', '.join(unknown)}; "
                                  f"available: {', '.join(available) or 'none'}")
            chosen = [s for s in available if s in self.scenes]
        if self.from_scene is not None:
            if self.from_scene not in available:
                raise ConfigError(f"{where}: ${{from_scene}} {self.from_scene!r} is not a scene; "
                                  f"available: {', '.join(available) or 'none'}")
            chosen = [s for s in chosen if s >= self.from_scene]
        return chosen

    def pick_frames(self, frames: list[int]) -> list[int]:
        """First frames of the selected pairs, from the sorted frame numbers of one scene."""
        present = set(frames)
        starts = [f for f in frames if f + 1 in present]
        if self.first_frame is not None:
            starts = [f for f in starts if f >= self.first_frame]
        if self.frames_per_scene is not None:
            starts = starts[: self.frames_per_scene]
        return starts


def numbering_gap(selection: Selection, frames: list[int]) -> Optional[str]:
    """What missing frame numbers of a scene change in the selection, or None when nothing.

    Pairs are consecutive numbers, so a missing frame removes the two pairs it belongs to, and
    ``frames_per_scene`` then counts from the pairs that are left (it takes others than with the
    frame present): the warning names the missing frames, the pairs lost and those taken instead.
    """
    if not frames:
        return None
    present = set(frames)
    missing = [f for f in range(frames[0], frames[-1] + 1) if f not in present]
    if not missing:
        return None
    complete = selection.pick_frames(list(range(frames[0], frames[-1] + 1)))
    chosen = selection.pick_frames(frames)
    lost = [f for f in complete if f not in chosen]
    if not lost:
        return None
    extra = [f for f in chosen if f not in complete]
    text = (f"gap in the frame numbering: no {plural('frame', len(missing))} {_numbers(missing)}, "
            f"so the {plural('pair', len(lost))} of frames {_pairs(lost)} cannot be formed")
    if extra:
        text += (f" and the selection takes the {plural('pair', len(extra))} of frames "
                 f"{_pairs(extra)} instead")
    return text


def _runs(values: list[int]) -> list[list[int]]:
    """Sorted integers split into runs of consecutive ones."""
    runs: list[list[int]] = []
    for v in values:
        if runs and v == runs[-1][-1] + 1:
            runs[-1].append(v)
        else:
            runs.append([v])
    return runs


def _numbers(values: list[int]) -> str:
    """``1, 4-6, 9``: sorted integers with runs joined."""
    return ", ".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in _runs(values))


def _pairs(firsts: list[int]) -> str:
    """Pairs named by their frames, from their first frames: ``1-2, 2-3`` for [1, 2], ``4-5 to
    9-10`` for [4, ..., 9] (a pair's first frame alone, or a range of them, reads as one pair)."""
    out = []
    for r in _runs(firsts):
        named = [f"{f}-{f + 1}" for f in r]
        out.append(", ".join(named) if len(named) <= 2 else f"{named[0]} to {named[-1]}")
    return ", ".join(out)


def frame_numbers(folder: Path, pattern) -> list[int]:
    """Sorted frame numbers of the files in ``folder`` whose names match ``pattern``.

    ``pattern`` is a compiled regular expression whose first group is the number.
    """
    found = []
    for p in Path(folder).iterdir():
        m = pattern.match(p.name)
        if m:
            found.append(int(m.group(1)))
    return sorted(found)


#: What each file key of the readers holds, for messages.
FILE_ROLES = {
    "image1": "first frame", "image2": "second frame", "depth1": "frame-1 depth",
    "depth2": "frame-2 depth", "disp1": "frame-1 disparity", "disp2": "frame-2 disparity",
    "flow": "ground-truth flow", "objects": "object map", "calib": "calibration",
    "cameras": "camera", "intrinsics": "intrinsics", "extrinsics": "extrinsics",
    "cam1": "frame-1 camera", "cam2": "frame-2 camera", "disp2_own": "frame-2 disparity",
}

ERROR, WARNING = "error", "warning"


@dataclass(frozen=True)
class Problem:
    """One problem found by checking: ``kind`` says what is wrong (problems of one kind are listed
    together), ``where`` names the file, frame or folder; warnings leave a pair readable."""

    kind: str
    where: str = ""
    severity: str = ERROR


@dataclass(frozen=True)
class NativeFlow:
    """How a dataset stores its ground-truth flow, so that outputs can write the flow in the same
    form beside Sintel's ``.flo``: the folder name (``flow_occ``) and the file format (``"kitti-png"``:
    KITTI's 16-bit PNG of u, v and valid; ``"flo5"``: Spring's HDF5, NaN where not valid)."""

    folder: str
    format: str


@dataclass(frozen=True)
class PairRef:
    """A frame pair as listed: its identity and the files it is read from (None when missing)."""

    id: PairId
    files: dict = field(default_factory=dict, compare=False, hash=False)


class Dataset(ABC):
    """A dataset on disk: lists its pairs and loads them as :class:`FramePair` records."""

    #: Registry name, e.g. ``"sintel"``.
    name: str = ""
    #: Keys of :attr:`PairRef.files` that every pair needs for weather (images, depth, cameras).
    required_files: tuple[str, ...] = ()
    #: How flow networks pad this dataset's frames in its benchmark protocol: "even" (top and
    #: bottom alike, as on Sintel) or "bottom" (KITTI); see :mod:`weathergen.models.padding`.
    padding: str = "even"
    #: Frames per second of the dataset's sequences: a weather field's particles move
    #: ``velocity / frame_rate`` per frame (unless the preset sets its own ``frame_rate``). Data
    #: without a recorded rate gets 30.
    frame_rate: float = 30.0
    #: True where the dataset has one rendering of its frames (no ``pass_`` to choose).
    single_pass: bool = True
    #: True where every pixel has a depth; False where the reader gives pixels without a
    #: measurement (sky) its ``far_depth``.
    dense_depth: bool = True
    #: The form of the dataset's own ground-truth flow that outputs also write, None for none
    #: beyond Sintel's ``.flo``.
    native_flow: Optional[NativeFlow] = None
    #: The reader's own keyword options (beyond the selection and the depth options every reader
    #: with depth takes), which the command line offers only for the readers that list them.
    options: tuple[str, ...] = ()
    #: True where the dataset has a second (right) camera that stereo rendering reads through
    #: :meth:`right_camera` (see :mod:`weathergen.datasets.stereo`).
    stereo: bool = False

    def __init__(self, root: str | Path, selection: Selection = Selection()):
        self.root = Path(root)
        self.selection = selection
        #: problems of whole scenes found by the last :meth:`pairs` (see :meth:`scene_problems`)
        self._listing_problems: dict[str, list[Problem]] = {}
        if not self.root.exists():
            raise DatasetError(f"{self.root}: dataset root does not exist")
        if not self.root.is_dir():
            raise DatasetError(f"{self.root}: dataset root is not a folder")

    @abstractmethod
    def pairs(self) -> list[PairRef]:
        """The selected pairs, sorted by scene then frame. Lists files only; reads nothing."""

    def no_pairs_message(self) -> str:
        """The one line for a selection that holds no frame pair: the options that emptied it and,
        when ``first_frame`` did, where the pairs start without it."""
        sel = self.selection
        message = f"{self.root}: the selection holds no frame pairs"
        narrowing = sel.narrowing()
        if not narrowing:
            return f"{message} (split {sel.split!r})"
        message += f" ({', '.join(narrowing)})"
        if sel.first_frame is not None:
            wider = copy.copy(self)
            wider.selection = replace(sel, first_frame=None)
            try:
                starts = sorted({ref.id.frame for ref in wider.pairs()})
            except WeatherGenError:
                starts = []
            if starts:
                message += "; without ${first_frame} the pairs start at " + (
                    f"frames {starts[0]} to {starts[-1]}" if len(starts) > 1 else f"frame {starts[0]}")
        return message

    def all_scenes(self) -> Optional[list[str]]:
        """Every scene of the split, before the selection; None for a reader without scenes."""
        return None

    @abstractmethod
    def load(self, ref: PairRef) -> FramePair:
        """Read and validate one pair; raise a :class:`WeatherGenError` naming the faulty file."""

    def describe(self) -> dict:
        """What was read, for manifests: name, root, selection and reader options."""
        sel = self.selection
        return {
            "dataset": self.name,
            # absolute, so that a manifest read from another folder (preview, evaluate, a
            # resume given the absolute path) names the same place
            "root": str(self.root.absolute()),
            "split": sel.split,
            "pass": sel.pass_,
            "scenes": list(sel.scenes) if sel.scenes else None,
            "from_scene": sel.from_scene,
            "frames_per_scene": sel.frames_per_scene,
            "first_frame": sel.first_frame,
        }

    def check(self, ref: PairRef) -> Optional[str]:
        """None if the pair reads cleanly, else a one-line description of the first problem
        (:func:`weathergen.datasets.checking.check_pair` lists them all).

        ``load`` names a missing file itself, with a hint where a split lacks it by design (the
        Sintel test split has no depth or cameras; KITTI testing, Spring test).
        """
        try:
            self.load(ref)
        except WeatherGenError as exc:
            return str(exc)
        return None

    # -- checking (see weathergen.datasets.checking) -----------------------------------------------
    def needed_files(self, ref: PairRef) -> tuple[str, ...]:
        """Keys of ``ref.files`` the pair cannot be read without."""
        return self.required_files

    def missing_hint(self, key: str) -> str:
        """Said after "file is missing" where a split lacks a file by design (a test split)."""
        return ""

    def missing_files(self, ref: PairRef) -> list[Problem]:
        """One problem per needed file that does not exist (all of them, not only the first)."""
        out = []
        for key in self.needed_files(ref):
            path = ref.files.get(key)
            if path is None or not Path(path).exists():
                # "frame-1 depth" and "frame-2 depth" are one kind of problem: "depth"
                role = FILE_ROLES.get(key, key).replace("frame-1 ", "").replace("frame-2 ", "")
                role = {"first frame": "frame", "second frame": "frame"}.get(role, role)
                out.append(Problem(f"{role} file is missing{self.missing_hint(key)}", str(path)))
        return out

    def scene_problems(self) -> dict[str, list[Problem]]:
        """Problems of whole scenes found by the last :meth:`pairs` (scene -> problems), such as
        gaps in the frame numbering (warnings)."""
        return dict(self._listing_problems)

    def scene_notes(self) -> list[str]:
        """:meth:`scene_problems` as lines for a run's notes (``"FOLDER: what"``)."""
        return [f"{p.where}: {p.kind}" if p.where else p.kind
                for problems in self.scene_problems().values() for p in problems]

    def _note_gaps(self, scene: str, frames: list[int], folder: Path) -> None:
        """Record a warning when missing frame numbers change the selection (see
        :func:`numbering_gap`)."""
        gap = numbering_gap(self.selection, frames)
        if gap:
            self._listing_problems[scene] = [Problem(gap, str(folder), WARNING)]

    def pair_warnings(self, ref: PairRef, pair: FramePair) -> list[Problem]:
        """Warnings about a pair that loaded: those the reader put in ``pair.meta["warnings"]``
        (``"FILE: what"`` lines; frames of which one is grey, the other colour), and whatever a
        reader adds (little valid depth)."""
        out = []
        for line in pair.meta.get("warnings", []):
            where, _, kind = line.partition(": ")
            out.append(Problem(kind, where, WARNING) if kind else Problem(line, "", WARNING))
        return out

    def right_camera(self, pair: FramePair):
        """The second camera of ``pair`` (a :class:`~weathergen.datasets.stereo.RightCamera`), for
        readers whose :attr:`stereo` is True; call it through
        :func:`weathergen.datasets.right_camera`, which refuses the others."""
        raise ConfigError(f"dataset {self.name!r} has no second camera")

    def pair_notes(self, pair: FramePair) -> list[str]:
        """Figures worth showing for a loaded pair (KITTI: the camera motion); none by default."""
        return []

    def __iter__(self):
        for ref in self.pairs():
            yield self.load(ref)

    def __len__(self) -> int:
        return len(self.pairs())
