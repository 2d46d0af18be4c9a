"""How much memory a run may still take: the machine's, its control group's, or a budget given.

:func:`available_memory` reads what the kernel says is available (``MemAvailable`` of
``/proc/meminfo``: free memory plus what can be reclaimed without swapping) and, where the process
runs in a control group with a memory limit (containers, job schedulers: cgroup v2
``memory.max``, v1 ``memory.limit_in_bytes``), that limit less the group's usage; the smaller
wins. The environment variable :data:`BUDGET_VARIABLE` (``WEATHERGEN_MEMORY_BUDGET=2G``) sets the
budget instead (to keep a run well below what the machine has, and in tests). No torch: CUDA
memory is the engine's to ask (:func:`weathergen.engine.rendering.budget.room_on`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import NamedTuple, Optional

from .errors import ConfigError, WeatherGenError

#: The environment variable that sets the memory budget (bytes; suffixes K, M, G, T: powers of 1024).
BUDGET_VARIABLE = "WEATHERGEN_MEMORY_BUDGET"

_UNITS = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


class Available(NamedTuple):
    """Bytes a run may still take, and where the figure comes from (for messages)."""

    bytes: int
    source: str


def parse_bytes(text: str) -> int:
    """``"512M"`` -> 536870912; a plain number is bytes; K, M, G, T (optionally followed by B or
    iB) are powers of 1024. Raises ValueError for anything else."""
    match = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*([KMGT]?)(?:i?B)?\s*", str(text), re.I)
    if match is None:
        raise ValueError(f"{text!r} is not an amount of memory (e.g. 512M, 4G)")
    return int(float(match.group(1)) * _UNITS[match.group(2).upper()])


def human_bytes(n: float) -> str:
    """``1536 * 2**20`` -> ``"1.5 GiB"``."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


#: What the allocators say when they cannot get memory: torch's CPU allocator (a RuntimeError),
#: CUDA's (torch.OutOfMemoryError); NumPy and Python raise MemoryError.
_OUT_OF_MEMORY = re.compile(r"can't allocate memory|CUDA out of memory|out of memory", re.I)


def out_of_memory(exc: BaseException) -> Optional[str]:
    """What ``exc`` says about memory when it is an allocation that failed (MemoryError, torch's
    OutOfMemoryError, torch's CPU allocator's RuntimeError), in a few words: "tried to allocate
    1.0 GiB"; None for any other error."""
    text = str(exc)
    if not (isinstance(exc, MemoryError) or type(exc).__name__ == "OutOfMemoryError"
            or (isinstance(exc, RuntimeError) and _OUT_OF_MEMORY.search(text))):
        return None
    asked = re.search(r"allocate (\d+) bytes", text)
    if asked:
        return f"tried to allocate {human_bytes(int(asked.group(1)))}"
    asked = re.search(r"allocate ([0-9.]+ [KMGTP]i?B)", text)
    return f"tried to allocate {asked.group(1)}" if asked else "an allocation failed"


def failure_message(exc: Exception, fewer: str) -> str:
    """The message of a pair that failed with ``exc``: a user error's own words, or for an
    allocation that failed (an estimate fell short, or something else took the memory meanwhile)
    what to lower (``fewer``: the options that draw fewer pairs at once). Any other error is
    raised again: a bug, to be seen."""
    if isinstance(exc, WeatherGenError):
        return str(exc)
    short = out_of_memory(exc)
    if short is None:
        raise exc
    return (f"ran out of memory ({short}); lower the preset's particle count or density (or its "
            f"far depth), or draw fewer pairs at once ({fewer})")


def available_memory(environ: Optional[dict] = None, root: Path = Path("/")) -> Optional[Available]:
    """What the process may still allocate (see the module's description), or None where nothing
    says (not Linux, no budget given). ``environ`` and ``root`` stand in for ``os.environ`` and
    the file system's root (tests). Raises ConfigError for a budget that is not an amount."""
    environ = os.environ if environ is None else environ
    if environ.get(BUDGET_VARIABLE, "").strip():
        try:
            return Available(parse_bytes(environ[BUDGET_VARIABLE]), BUDGET_VARIABLE)
        except ValueError as exc:
            raise ConfigError(f"{BUDGET_VARIABLE}: {exc}") from None
    found = []
    meminfo = _read(root / "proc/meminfo")
    match = re.search(r"^MemAvailable:\s+(\d+)\s*kB", meminfo or "", re.M)
    if match:
        found.append(Available(int(match.group(1)) * 1024, "MemAvailable"))
    group = _cgroup_room(root)
    if group is not None:
        found.append(group)
    return min(found, key=lambda a: a.bytes) if found else None


def _read(path: Path) -> Optional[str]:
    try:
        return path.read_text()
    except OSError:
        return None


def _cgroup_room(root: Path) -> Optional[Available]:
    """The process's control group's memory limit less its usage, where it has a limit."""
    lines = (_read(root / "proc/self/cgroup") or "").splitlines()
    for line in lines:                              # cgroup v2: "0::/path"
        if line.startswith("0::"):
            folder = root / "sys/fs/cgroup" / line[3:].lstrip("/")
            limit, used = _read(folder / "memory.max"), _read(folder / "memory.current")
            if limit and used and limit.strip().isdigit():
                return Available(max(0, int(limit) - int(used)), "the control group's memory.max")
    for line in lines:                              # cgroup v1: "N:memory:/path"
        parts = line.split(":", 2)
        if len(parts) == 3 and "memory" in parts[1].split(","):
            folder = root / "sys/fs/cgroup/memory" / parts[2].lstrip("/")
            if not folder.is_dir():
                folder = root / "sys/fs/cgroup/memory"
            limit = _read(folder / "memory.limit_in_bytes")
            used = _read(folder / "memory.usage_in_bytes")
            if limit and used and int(limit) < 1 << 60:     # "no limit" is a huge number
                return Available(max(0, int(limit) - int(used)),
                                 "the control group's memory.limit_in_bytes")
    return None
