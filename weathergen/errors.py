"""The exceptions weathergen raises for bad input.

Every error a user can cause derives from :class:`WeatherGenError`; the command-line layer turns
them into one line on stderr and a non-zero exit code. Anything else that escapes is a bug and keeps
its traceback.
"""

from __future__ import annotations

from pathlib import Path


class WeatherGenError(Exception):
    """Base class of all user-facing errors."""


class FormatError(WeatherGenError):
    """A file exists but its content is not what its format promises.

    The message always starts with the file's path, so it is useful on its own.
    """

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class DatasetError(WeatherGenError):
    """A dataset tree is missing, incomplete or inconsistent (missing files, size mismatches)."""


class ConfigError(WeatherGenError):
    """An invalid option, preset, or selection."""


class WriteError(WeatherGenError):
    """An output cannot be written (disk full, no permission, read-only file system).

    The message names the file that was to be written (never a temporary name) and the reason.
    """
