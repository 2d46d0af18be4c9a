"""Putting a folder of frames in order without guessing, whatever the file names.

Rules (also in docs/datasets.md, "Your own data"):

1. The frames are the image files of the folder (``.png``, ``.jpg``, ``.jpeg``), or, with a
   pattern (a shell glob such as ``*_left.png``), the files whose names match it.
2. Names are compared by their *kind*: the name with every run of digits replaced by ``#``
   (``000012_left.png`` is of kind ``#_left.png``). Frames of several kinds (left and right
   images, or a stray ``cover.png`` among numbered frames) cannot be put in one order without
   guessing: that is a problem, and the message suggests a pattern. Names without digits at all
   are sorted by name.
3. Where the names differ in exactly one run of digits, that run is the frame number and sets the
   order (numerically: ``frame9`` before ``frame10``). Otherwise (no digits, or several runs that
   change, such as a date and a time) the frames are in natural order (digit runs compared as
   numbers) and the frame number is the position in that order, from 0.
4. Consecutive frames in that order are the pairs.

Nothing here reads images; :func:`order_frames` works on names.
"""

from __future__ import annotations

import fnmatch
import re
from collections import Counter
from dataclasses import dataclass
from typing import Optional

from ..words import counted

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_DIGITS = re.compile(r"\d+")


@dataclass(frozen=True)
class FrameOrder:
    """Frames in order: ``frames`` is a list of ``(number, name)``; ``numbering`` says where the
    numbers come from ("name" or "position"); ``problem`` is set (and ``frames`` empty) when the
    names cannot be put in order."""

    frames: tuple = ()
    numbering: str = "name"
    problem: Optional[str] = None


def _natural_key(name: str):
    return [(0, int(part), "") if part.isdigit() else (1, 0, part)
            for part in re.split(r"(\d+)", name) if part]


def _examples(names: list[str], at_most: int = 2) -> str:
    return ", ".join(names[:at_most]) + (", ..." if len(names) > at_most else "")


def order_frames(names: list[str], pattern: Optional[str] = None) -> FrameOrder:
    """Order the frame files among ``names`` (file names of one folder) by the rules above."""
    if pattern is not None:
        frames = sorted(n for n in names if fnmatch.fnmatchcase(n, pattern))
        if not frames:
            return FrameOrder(problem=f"no file matches the frame pattern {pattern!r} "
                                      f"({counted(len(names), 'file')} there"
                                      f"{': ' + _examples(sorted(names)) if names else ''})")
    else:
        frames = sorted(n for n in names if n.lower().endswith(IMAGE_SUFFIXES))
        if not frames:
            others = Counter(("." + n.rsplit(".", 1)[-1].lower()) if "." in n else "no suffix"
                             for n in names)
            found = ", ".join(f"{c} {s}" for s, c in sorted(others.items()))
            return FrameOrder(problem=f"holds no image files ({', '.join(IMAGE_SUFFIXES)})"
                                      + (f"; found {found}" if found else ""))
    if len(frames) < 2:
        return FrameOrder(problem=f"holds a single frame ({frames[0]}); a pair needs two")

    kinds: dict[str, list[str]] = {}
    for n in frames:
        kinds.setdefault(_DIGITS.sub("#", n), []).append(n)     # the name, its numbers as #
    if len(kinds) > 1 and any(_DIGITS.search(n) for n in frames):
        listed = "; ".join(f"{k!r}: {counted(len(v), 'file')} ({_examples(v)})"
                           for k, v in sorted(kinds.items(), key=lambda kv: -len(kv[1]))[:4])
        biggest = max(kinds.items(), key=lambda kv: len(kv[1]))[0]
        suggestion = biggest.replace("#", "*")
        return FrameOrder(problem=f"holds frames named in {len(kinds)} ways, which cannot be put in "
                                  f"one order without guessing: {listed}; choose one with a frame "
                                  f"pattern (e.g. --frame-pattern '{suggestion}')")

    runs = [[int(d) for d in _DIGITS.findall(n)] for n in frames]
    varying = [i for i in range(len(runs[0])) if len({r[i] for r in runs}) > 1] if kinds and \
        len(kinds) == 1 else []
    if len(kinds) == 1 and runs[0] and not varying:
        # the names differ, but not in any number: only in zero padding (f01, f1)
        return FrameOrder(problem=f"frames {frames[0]} and {frames[1]} have the same number "
                                  f"{runs[0][-1] if len(runs[0]) == 1 else runs[0]}")
    if len(varying) == 1:
        i = varying[0]
        numbered = sorted(((r[i], n) for r, n in zip(runs, frames)), key=lambda x: x[0])
        seen: dict[int, str] = {}
        for number, n in numbered:
            if number in seen:
                return FrameOrder(problem=f"frames {seen[number]} and {n} have the same number {number}")
            seen[number] = n
        return FrameOrder(frames=tuple(numbered), numbering="name")
    ordered = sorted(frames, key=_natural_key)
    return FrameOrder(frames=tuple(enumerate(ordered)), numbering="position")
