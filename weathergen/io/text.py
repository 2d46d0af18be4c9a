"""Reading small text files (calibrations, camera lists) with errors that name the file."""

from __future__ import annotations

from pathlib import Path

from ..errors import FormatError


def read_text_file(path: str | Path, kind: str) -> str:
    """The text of ``path``; :class:`FormatError` saying "<kind> file not found" or why it is unreadable."""
    path = Path(path)
    try:
        return path.read_text()
    except FileNotFoundError:
        raise FormatError(path, f"{kind} file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(path, f"cannot be read as text ({exc})") from None
