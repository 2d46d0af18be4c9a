"""Claiming an output folder for a run: one writer at a time, the folder's earlier run, resume and
overwrite, a killed run's temporary files, and undoing a folder that came to nothing.

Render and attack claim their folders the same way, through :func:`claim_folder`, each with its
own marker file, so that neither writes into the other's folder, nor into a folder of the user's.
"""

from __future__ import annotations

import contextlib
import glob
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, Optional

from ..errors import ConfigError, NothingRendered
from ..io.lock import FolderLock, Holder
from .manifest import (MANIFEST, MANIFEST_PARTS, RUN_CONFIG, SUMMARY, jsonable, read_attack_manifest,
                       read_run_config, shard_part, write_run_config)


@dataclass(frozen=True)
class FolderKind:
    """What kind of run owns a folder, and how messages speak of it."""

    marker: str             # file that says the folder is ours
    marker_text: str
    foreign: str            # the end of the message for a non-empty folder without the marker
    holds: str              # "a render"
    done: str               # "rendered"
    #: where a run records the settings every later run in the folder must share: "run-config"
    #: (``manifest.d/.config.json``, written as the folder is claimed, so that the shards of a
    #: render compare with it) or "manifest" (the attack manifest's ``config``)
    settings: str = "run-config"


RENDER_FOLDER = FolderKind(
    ".weathergen-render", "weathergen render output\n",
    "was not created by weathergen render (use ${overwrite} to write into it anyway)",
    "a render", "rendered", "run-config")
ATTACK_FOLDER = FolderKind(
    ".weathergen-attack", "weathergen attack output\n",
    "was not written by weathergen attack (use another ${out}, or ${overwrite})",
    "an attack", "attacked", "manifest")


def lock_file(shard: tuple[int, int] = (1, 1)) -> str:
    """The name of a run's lock file: one per shard (the shards of one run write one folder at the
    same time), one for an unsharded run."""
    i, n = shard
    return ".weathergen-lock" if n == 1 else f".weathergen-lock-shard-{i}-of-{n}"


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
    the same configuration, or ``overwrite``. A run that goes on in a folder of ``kind``
    (resuming, overwriting, or after a run killed before it recorded anything) removes the
    temporary files that a killed run left: with ``temporary``, only those in the given places
    (``(folder, name prefix)`` pairs: other shards may be writing elsewhere), else every one below
    ``out``.
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
    if (out / kind.marker).exists() and out.is_dir():
        # temporary files of a killed run (atomic writes that never reached their rename; an
        # EXR's end in .tmp.exr): resumed, redone, or killed before it recorded anything
        if temporary is None:
            stale_files = out.rglob(".*.tmp*")
        else:
            stale_files = (p for folder, prefix in temporary
                           for p in Path(folder).glob(f"{glob.escape(prefix)}*.tmp*"))
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


@dataclass
class Claim:
    """A folder claimed by :func:`claim_folder`, for the run inside its block."""

    out: Path
    lock: FolderLock
    #: True when the folder did not exist before the claim
    created: bool
    #: what the folder's earlier run recorded (None when there was none, or with ``overwrite``): the
    #: settings of a render folder, the whole manifest of an attack folder
    previous: Optional[dict]
    #: the holder recorded by a run that ended without releasing the lock (killed), or None
    stale: Optional[Holder]


@contextlib.contextmanager
def claim_folder(out: Path, kind: FolderKind, config: dict, *, resume: bool, overwrite: bool,
                 shard: tuple[int, int] = (1, 1),
                 temporary: Optional[Iterable[tuple[Path, str]]] = None,
                 on_note: Callable[[str], None] = lambda text: None) -> Iterator[Claim]:
    """Claim ``out`` for a run with settings ``config``, for the duration of the block.

    In order: a folder that is not ``kind``'s (and that ``overwrite`` does not allow) is refused
    before anything is created in it; the folder is created and its lock taken (another run holding
    it raises :class:`~weathergen.errors.FolderBusy`; a killed run's stale lock is taken over and
    reported through ``on_note``); under the lock, the earlier run's record is read and checked
    (:func:`prepare_folder`: ``resume`` with the same settings, or ``overwrite``; a new shard of a
    sharded render may start in a folder other shards wrote), a resumed run's leftover temporary
    files are removed (only those in ``temporary``'s places where given) and a render records its
    settings. When the block raises :class:`~weathergen.errors.NothingRendered` in a folder the
    claim created, the folder is removed again. The lock is released, and its file removed, however
    the block ends; a disk error while claiming is one :class:`ConfigError` line.
    """
    out = Path(out)
    name = lock_file(shard)
    created = not out.exists()
    if is_foreign(out, kind, overwrite, ignore=(name,)):
        prepare_folder(out, kind, config, None, resume=resume, overwrite=overwrite, ignore=(name,))
    try:
        out.mkdir(parents=True, exist_ok=True)
        lock = FolderLock(out / name, str(out)).acquire()
    except OSError as exc:
        raise ConfigError(f"{out}: cannot write here ({exc.strerror})") from None
    try:
        if lock.stale is not None:
            on_note(f"{out}: took over the stale lock of {lock.stale} (that run ended without "
                    f"releasing it, e.g. killed)")
        try:
            # Read under the lock: what the run before us recorded is final.
            previous = None if overwrite else earlier_record(out, kind)
            settings = None if previous is None else (
                previous.get("config", {}) if kind.settings == "manifest" else previous)
            # A new shard of a sharded run may start in a folder that other shards have written.
            other_shard = shard[1] > 1 and not shard_part(out, shard).exists()
            if temporary is not None:       # and the run's own bookkeeping
                temporary = [*temporary, *_bookkeeping_places(out, shard)]
            prepare_folder(out, kind, config, settings, resume=resume, overwrite=overwrite,
                           shared=other_shard, ignore=(name,), temporary=temporary)
            if kind.settings == "run-config":
                write_run_config(out, config)
        except OSError as exc:
            raise ConfigError(f"{out}: cannot write here ({exc.strerror})") from None
        claim = Claim(out, lock, created, previous, lock.stale)
        try:
            yield claim
        except NothingRendered:
            if created:
                _remove_bookkeeping(out, kind, shard)
            raise
    finally:
        lock.release()
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()             # only where nothing is left in it


def earlier_record(out: Path, kind: FolderKind) -> Optional[dict]:
    """What the run before recorded in a folder of ``kind``: the settings of a render folder, the
    manifest of an attack folder; None for a folder without the marker or without a record."""
    out = Path(out)
    if not (out / kind.marker).exists():
        return None
    if kind.settings == "run-config":
        return read_run_config(out)
    return read_attack_manifest(out) if (out / MANIFEST).exists() else None


def _bookkeeping_places(out: Path, shard: tuple[int, int]) -> list[tuple[Path, str]]:
    """Where a killed run of ``shard`` may have left temporary bookkeeping files, as ``(folder, name
    prefix)``: its manifest part; the folder's settings, manifest and summary when unsharded (the
    shards of a run share those, and another may be writing them)."""
    places = [(out / MANIFEST_PARTS, f".{shard_part(out, shard).name}.")]
    if shard[1] == 1:
        places += [(out / MANIFEST_PARTS, f".{RUN_CONFIG}."), (out, f".{MANIFEST}."),
                   (out, f".{SUMMARY}.")]
    return places


def _remove_bookkeeping(out: Path, kind: FolderKind, shard: tuple[int, int]) -> None:
    """Undo a folder a run created and wrote nothing into but its bookkeeping (every pair failed).

    Only known files and empty folders are removed, never a tree: whatever else is there stays. The
    lock file goes when the lock is released, and the folder itself when that leaves it empty.
    """
    for path in (out / MANIFEST, out / SUMMARY, out / kind.marker, out / MANIFEST_PARTS / RUN_CONFIG,
                 shard_part(out, shard)):
        with contextlib.suppress(OSError):
            path.unlink()
    for folder in sorted((p for p in out.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
        with contextlib.suppress(OSError):
            folder.rmdir()
