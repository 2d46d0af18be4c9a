"""The exceptions weathergen raises for bad input.

Every error a user can cause derives from :class:`WeatherGenError`; the command-line layer turns
them into one line on stderr and a non-zero exit code. Anything else that escapes is a bug and keeps
its traceback. Every error class of the package is declared here.

Messages speak of parameters, not of command-line options: a message refers to a parameter as
``${name}`` (``"${steps} must be >= 0"``). ``str(error)`` writes the parameter's name
(``steps must be >= 0``); the command line writes its option instead (``--steps must be >= 0``)
through :meth:`WeatherGenError.render`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Callable

_PARAMETER = re.compile(r"\$\{([a-z_][a-z0-9_]*)\}")


class WeatherGenError(Exception):
    """Base class of all user-facing errors."""

    def render(self, spell: Callable[[str], str] = lambda name: name) -> str:
        """The message with every ``${name}`` written as ``spell(name)``."""
        return _PARAMETER.sub(lambda m: spell(m.group(1)), super().__str__())

    def __str__(self) -> str:
        return self.render()


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


class ShapeError(WeatherGenError, ValueError):
    """A tensor handed to the library has the wrong shape, dtype or size for what it is used for
    (frames of different sizes, a depth map that is not (B, 1, H, W), a flow of the wrong size).

    The message names the tensor and says what was expected and what was found. It is also a
    ValueError, the exception Python code expects for a bad argument.
    """


class OutputError(WeatherGenError):
    """An output cannot be written (disk full, no permission, read-only file system).

    The message names the file that was to be written (never a temporary name) and the reason.
    """


class FolderBusy(ConfigError):
    """Another run holds the lock of an output folder (the message names it: pid and host)."""


class NothingRendered(DatasetError):
    """Every selected pair of a run failed to load or render: nothing usable was written."""
