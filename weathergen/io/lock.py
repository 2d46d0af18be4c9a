"""One writer per output folder: an advisory lock file held for the whole run.

The lock is an ``flock`` on a small file in the folder, so the operating system releases it when
its holder ends in any way, ``kill -9`` included: a lock is never left "held" by a dead process.
The file also records who holds it (process id, host, start time), for two messages: a second
writer is told which process holds the folder, and a run that finds the record of a holder that
did not release it (a killed run) reports that stale lock as it takes it over.

Releasing removes the file, while still holding it, so that a finished run leaves no lock file
behind. Deleting a lock file that another process has just opened could let two processes hold
"the" lock (one on the deleted file, one on a new one), so taking the lock checks, once held, that
the file it holds is still the one at the path, and starts again otherwise.
"""

from __future__ import annotations

import json
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from ..errors import FolderBusy

try:
    import fcntl
except ImportError:                         # Windows: no advisory locks, runs are not guarded
    fcntl = None


@dataclass(frozen=True)
class Holder:
    """Who holds (or held) a lock."""

    pid: int
    host: str
    since: str = ""

    def __str__(self) -> str:
        return f"pid {self.pid} on {self.host}" + (f", since {self.since}" if self.since else "")


class FolderLock:
    """An exclusive lock on ``path``; use as a context manager or call :meth:`acquire`/:meth:`release`.

    After :meth:`acquire`, :attr:`stale` is the holder recorded by a run that ended without releasing
    the lock (killed), or None.
    """

    def __init__(self, path: str | Path, what: str = "folder"):
        self.path = Path(path)
        self.what = what
        self.stale: Optional[Holder] = None
        self._fd: Optional[int] = None

    def acquire(self) -> "FolderLock":
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
            try:
                if fcntl is not None:
                    try:
                        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    except BlockingIOError:
                        holder = _parse(_read(fd))
                        who = str(holder) if holder else "a process that has not recorded itself yet"
                        raise FolderBusy(f"{self.what} is being written by another weathergen run "
                                         f"({who}); wait for it to finish, or choose another "
                                         f"${{out}}") from None
            except BaseException:
                os.close(fd)
                raise
            if _is_at(fd, self.path):
                break
            os.close(fd)            # its holder removed it as we opened it: take the one there now
        try:
            self.stale = _parse(_read(fd))
            record = json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                                 "since": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
            os.ftruncate(fd, 0)
            os.pwrite(fd, record.encode(), 0)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        return self

    def release(self) -> None:
        """Remove the lock file (still held, so that no one else holds it) and let go of it. Where
        it cannot be removed, it is emptied: the next run then finds no holder's record in it."""
        if self._fd is None:
            return
        try:
            if _is_at(self._fd, self.path):
                self.path.unlink()
        except OSError:
            try:
                os.ftruncate(self._fd, 0)
            except OSError:
                pass                          # a full disk cannot stop the release
        finally:
            os.close(self._fd)                # closing drops the flock
            self._fd = None

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _is_at(fd: int, path: Path) -> bool:
    """True when the open file ``fd`` is the file at ``path`` (not one removed from there)."""
    try:
        here = os.stat(path)
    except OSError:
        return False
    held = os.fstat(fd)
    return (held.st_dev, held.st_ino) == (here.st_dev, here.st_ino)


def _read(fd: int) -> str:
    try:
        return os.pread(fd, 4096, 0).decode("utf-8", "replace")
    except OSError:
        return ""


def _parse(text: str) -> Optional[Holder]:
    if not text.strip():
        return None
    try:
        data = json.loads(text)
        return Holder(int(data["pid"]), str(data["host"]), str(data.get("since", "")))
    except (ValueError, KeyError, TypeError):
        return Holder(-1, "an unknown host")
