"""Atomic file writes: a reader never sees a half-written file, even after a crash or Ctrl-C.

Data goes to a hidden temporary file in the destination folder (``.NAME.PID.*.tmp``, PID the
writing process's), is flushed to disk, and is renamed over the destination in one step
(``os.replace`` is atomic on POSIX and Windows). A process killed outright can leave such a
temporary file behind; it never carries a final name, the next run in the same output folder
deletes it (``weathergen render --resume``, see :func:`~weathergen.outputs.folder.prepare_folder`),
and the writers of single files (a video, a contact sheet) delete those of their file whose writer
is gone before they write it (:func:`remove_temporaries`).
"""

from __future__ import annotations

import contextlib
import errno
import glob
import os
import re
import tempfile
from pathlib import Path

from ..errors import OutputError


def _read_umask() -> int:
    # The umask can only be read by setting it; set it straight back. Read once, at import, since
    # the brief window with a zero umask would affect files other threads create meanwhile.
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: The process umask, read at import: files and folders get 0o666 / 0o777 less this.
UMASK = _read_umask()


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; create parent folders as needed."""
    path = Path(path)
    with atomic_open(path) as f:
        f.write(data)
    return path


@contextlib.contextmanager
def atomic_open(path: str | Path):
    """Context manager yielding a binary file handle; the file appears at ``path`` only on success."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = ".tmp"):
    """Context manager yielding a temporary path to write; it is renamed to ``path`` on success.

    For writers that only take a file name (such as OpenEXR's). The file gets the permissions a
    plain ``open`` would give it (``0o666`` less the umask), not the owner-only ones of a
    temporary file, so outputs on a shared disk stay readable to the group.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=temporary_prefix(path), suffix=suffix, dir=path.parent)
    except OSError as exc:
        raise _naming(exc, path, None) from None
    try:
        os.fchmod(fd, 0o666 & ~UMASK)
        os.close(fd)
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise _naming(exc, path, tmp) from None
        raise


def temporary_prefix(path: str | Path) -> str:
    """The name with which this process's temporary files for ``path`` begin: ``.NAME.PID.``."""
    return f".{Path(path).name}.{os.getpid()}."


def remove_temporaries(path: str | Path, only_of_dead: bool = True) -> list[Path]:
    """Delete the temporary files that writes of ``path`` left in its folder (a killed writer's:
    ``.NAME.PID.XXXXXXXX`` with a temporary suffix); with ``only_of_dead``, only those whose
    writing process is gone (on this machine), so that a write in progress keeps its file.
    Returns what was deleted."""
    path = Path(path)
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(?:(\d+)\.)?[a-z0-9_]{{8}}"
                         rf"(?:\.tmp.*|{re.escape(path.suffix)})")
    removed = []
    try:
        candidates = list(path.parent.glob(f"{glob.escape('.' + path.name)}.*"))
    except OSError:
        return removed
    for tmp in candidates:
        match = pattern.fullmatch(tmp.name)
        if match is None or not tmp.is_file():
            continue
        if only_of_dead and match.group(1) is not None and _alive(int(match.group(1))):
            continue
        with contextlib.suppress(OSError):
            tmp.unlink()
            removed.append(tmp)
    return removed


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (this process does)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:                     # someone else's process
        return True
    return True


def _naming(exc: OSError, path: Path, tmp) -> OSError:
    """The same error, naming the destination instead of a temporary file (or of no file).

    An error that names another file (a parent folder that cannot be created) keeps that name: it
    is the place to fix.
    """
    ours = exc.filename is None or str(exc.filename) == str(tmp) or (
        Path(str(exc.filename)).name.startswith(f".{path.name}."))      # a temporary name
    if not ours:
        return exc
    if exc.errno is None:
        exc.filename, exc.filename2 = str(path), None
        return exc
    return type(exc)(exc.errno, exc.strerror, str(path))


#: errno values that mean "no room": the disk or the user's quota is full.
NO_SPACE = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}
#: errno values that mean "not allowed here": permissions, a read-only file system.
NOT_ALLOWED = {errno.EACCES, errno.EPERM, errno.EROFS}


def write_error(exc: OSError, fallback: str | Path, hint: str = "") -> OutputError:
    """A one-line :class:`~weathergen.errors.OutputError` for a failed write.

    It names the file (``exc.filename``, else ``fallback``) and the reason in words; ``hint`` (for
    example "rerun with --resume") is appended after what to fix.
    """
    where = exc.filename or fallback
    reason = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno in NO_SPACE:
        fix = "free some space"
    elif exc.errno in NOT_ALLOWED:
        fix = "choose a writable place or fix the permissions"
    else:
        fix = ""
    then = "; ".join(x for x in (fix, hint) if x)
    return OutputError(f"{where}: cannot write ({reason})" + (f"; {then}" if then else ""))
