"""The formats of an output's weather frames: one module each, registered here by one line.

The registry is the one owner of how frames are written and read back: the writer of a pair
(:func:`~weathergen.outputs.pairs.write_pair_outputs`) writes every format an output asks for,
and whatever reads an output's frames (:class:`~weathergen.outputs.PairOutput`'s ``read_frame``,
used by ``evaluate``, ``preview`` and its videos) reads them through the format here. A new
format is a new module beside these (a :class:`FrameFormat`) and its line in
:data:`FRAME_FORMATS`; ``--format`` offers it, and ``both`` writes every registered format.
"""

from __future__ import annotations

from . import exr, png
from .base import FrameFormat

#: Every frame format, by name, in the order ``both`` writes them (the first is the one read).
FRAME_FORMATS: dict[str, FrameFormat] = {f.name: f for f in (
    png.FORMAT,
    exr.FORMAT,
)}
#: ``--format`` every registered format at once.
ALL = "both"
#: What ``--format`` takes.
FORMATS = (*FRAME_FORMATS, ALL)


def formats_of(fmt: str) -> tuple[FrameFormat, ...]:
    """The formats an output of ``--format fmt`` writes, in writing order."""
    if fmt == ALL:
        return tuple(FRAME_FORMATS.values())
    try:
        return (FRAME_FORMATS[fmt],)
    except KeyError:
        raise ValueError(f"unknown frame format {fmt!r}; known: {', '.join(FORMATS)}") from None


def read_format(fmt: str) -> FrameFormat:
    """The format a reader takes an output of ``--format fmt``'s frames from: the first written."""
    return formats_of(fmt)[0]


__all__ = ["ALL", "FORMATS", "FRAME_FORMATS", "FrameFormat", "formats_of", "read_format"]
