"""Claiming an output folder: refuse folders that are not ours or hold another run, then mark it.

Render and attack folders follow the same rules (:func:`prepare_folder`), each with its own
marker file, so that neither writes into the other's folder, nor into a folder of the user's.
"""

from __future__ import annotations

import contextlib
import glob
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Optional

from ..errors import ConfigError
from ..io.lock import FolderLock
from .manifest import jsonable


@dataclass(frozen=True)
class FolderKind:
    """What kind of run owns a folder, and how messages speak of it."""

    marker: str             # file that says the folder is ours
    marker_text: str
    foreign: str            # the end of the message for a non-empty folder without the marker
    holds: str              # "a render"
    done: str               # "rendered"


RENDER_FOLDER = FolderKind(
    ".weathergen-render", "weathergen render output\n",
    "was not created by weathergen render (use ${overwrite} to write into it anyway)",
    "a render", "rendered")
ATTACK_FOLDER = FolderKind(
    ".weathergen-attack", "weathergen attack output\n",
    "was not written by weathergen attack (use another ${out}, or ${overwrite})",
    "an attack", "attacked")


def is_foreign(out: Path, kind: FolderKind, overwrite: bool, ignore: Iterable[str] = ()) -> bool:
    """True when ``out`` is not a folder, or a non-empty folder without ``kind``'s marker that
    ``overwrite`` does not allow to write into (entries named in ``ignore`` do not count)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        return True
    skip = set(ignore)
    return (out.is_dir() and any(p.name not in skip for p in out.iterdir())
            and not (out / kind.marker).exists() and not overwrite)


def prepare_folder(out: Path, kind: FolderKind, config: dict, previous: Optional[dict], *,
                   resume: bool, overwrite: bool, shared: bool = False,
                   ignore: Iterable[str] = (),
                   temporary: Optional[Iterable[tuple[Path, str]]] = None) -> None:
    """Create or reuse ``out`` for a run with settings ``config``.

    ``previous`` is the configuration an earlier run recorded in the folder (None if none). A
    non-empty folder without ``kind``'s marker is refused unless ``overwrite`` (entries named in
    ``ignore``, such as the caller's lock file, do not count); a folder that holds a run is
    refused unless ``resume`` (or ``shared``: another shard of the same run may start in it) with
    the same configuration, or ``overwrite``. Resuming removes the temporary files that a killed
    run left: with ``temporary``, only those in the given places (``(folder, name prefix)``
    pairs: other shards may be writing elsewhere), else every one below ``out``.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder")
    skip = set(ignore)
    if out.exists() and any(p.name not in skip for p in out.iterdir()):
        if not (out / kind.marker).exists() and not overwrite:
            raise ConfigError(f"{out}: folder is not empty and {kind.foreign}")
        if previous is not None and not overwrite:
            if not resume and not shared:
                raise ConfigError(f"{out}: already holds {kind.holds} (use ${{resume}} to finish it, "
                                  f"or ${{overwrite}} to redo it)")
            new = jsonable(config)
            if previous != new:
                diff = sorted(k for k in set(previous) | set(new) if previous.get(k) != new.get(k))
                raise ConfigError(f"{out}: was {kind.done} with different settings "
                                  f"({', '.join(diff)}); use another ${{out}}, or ${{overwrite}}")
    if resume and out.is_dir():
        # temporary files of a killed run (atomic writes that never reached their rename)
        if temporary is None:
            stale_files = out.rglob(".*.tmp*")
        else:
            stale_files = (p for folder, prefix in temporary
                           for p in Path(folder).glob(f"{glob.escape(prefix)}*.tmp"))
        for stale in stale_files:
            if stale.is_file():
                stale.unlink()
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / kind.marker).write_text(kind.marker_text)
    except OSError as exc:
        raise ConfigError(f"{out}: cannot write here ({exc.strerror})") from None


def folder_size(root: Path) -> int:
    """Bytes of every file below ``root``."""
    return sum(p.stat().st_size for p in Path(root).rglob("*") if p.is_file())


def lock_folder(out: Path, kind: FolderKind, lock_file: str, config: dict, *, resume: bool,
                overwrite: bool) -> FolderLock:
    """Take the lock of run folder ``out`` (creating the folder), held, for the caller to release.

    A folder that is not ``kind``'s (and that ``overwrite`` does not allow) is refused with the
    reason before anything is created in it; a folder another run holds raises
    :class:`~weathergen.io.lock.FolderBusy`. Check the folder's earlier run under the lock, with
    :func:`prepare_folder` inside :func:`released_on_failure`.
    """
    out = Path(out)
    if is_foreign(out, kind, overwrite, ignore=(lock_file,)):
        prepare_folder(out, kind, config, None, resume=resume, overwrite=overwrite,
                       ignore=(lock_file,))
    try:
        out.mkdir(parents=True, exist_ok=True)
        return FolderLock(out / lock_file, str(out)).acquire()
    except OSError as exc:
        raise ConfigError(f"{out}: cannot write here ({exc.strerror})") from None


@contextlib.contextmanager
def released_on_failure(lock: FolderLock, out: Path) -> Iterator[None]:
    """Release ``lock`` when the block fails (a disk error becomes a one-line ConfigError)."""
    try:
        yield
    except OSError as exc:
        lock.release()
        raise ConfigError(f"{out}: cannot write here ({exc.strerror})") from None
    except BaseException:
        lock.release()
        raise
