"""Atomic file writes: a reader never sees a half-written file, even after a crash or Ctrl-C.

Data goes to a hidden temporary file in the destination folder (``.NAME.*.tmp``), is flushed to
disk, and is renamed over the destination in one step (``os.replace`` is atomic on POSIX and
Windows). A process killed outright can leave such a temporary file behind; it never carries a
final name, and ``weathergen render --resume`` deletes it.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


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
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~UMASK)
        os.close(fd)
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
