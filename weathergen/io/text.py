"""Reading small text files (presets, scale tables, calibrations, camera lists) with errors that
name the file."""

from __future__ import annotations

from pathlib import Path

from ..errors import FormatError


def read_text_file(path: str | Path, kind: str) -> str:
    """The UTF-8 text of ``path``.

    Raises :class:`FormatError` naming the file: "<kind> file not found", or why it cannot be read
    (no permission, a folder, bytes that are not UTF-8 text such as a binary file).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FormatError(path, f"{kind} file not found") from None
    except IsADirectoryError:
        raise FormatError(path, f"is a folder, not a {kind} file") from None
    except OSError as exc:
        raise FormatError(path, f"cannot read {kind} file ({exc.strerror or exc})") from None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FormatError(path, f"is not UTF-8 text (byte 0x{data[exc.start]:02x} at offset "
                                f"{exc.start}); a {kind} file must be a text file") from None
