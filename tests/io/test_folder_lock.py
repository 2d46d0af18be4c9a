"""The output-folder lock: one holder at a time, released by the OS when its holder dies, and the
record of a killed holder reported as stale."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys

import pytest

from weathergen.io.lock import FolderBusy, FolderLock, Holder

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="advisory locks are POSIX")


def test_second_holder_is_refused_with_the_first_ones_pid_and_host(tmp_path):
    path = tmp_path / ".lock"
    with FolderLock(path, "out"):
        with pytest.raises(FolderBusy) as info:
            FolderLock(path, "out").acquire()
        message = str(info.value)
        assert message.startswith("out is being written by another weathergen run (pid ")
        assert f"pid {os.getpid()} on {socket.gethostname()}" in message
    # released: the next holder finds a clean lock
    lock = FolderLock(path).acquire()
    assert lock.stale is None
    lock.release()


def test_lock_of_a_killed_process_is_free_and_reported_as_stale(tmp_path):
    path = tmp_path / ".lock"
    code = (f"from weathergen.io.lock import FolderLock; FolderLock({str(path)!r}).acquire(); "
            "print('held', flush=True); import time; time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE)
    assert proc.stdout.readline().strip() == b"held"
    with pytest.raises(FolderBusy, match=f"pid {proc.pid} on"):
        FolderLock(path).acquire()
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    lock = FolderLock(path).acquire()
    assert lock.stale is not None and (lock.stale.pid, lock.stale.host) == (proc.pid, socket.gethostname())
    lock.release()


def test_holder_text():
    assert str(Holder(12, "node7", "2026-01-01T00:00:00+0000")) == "pid 12 on node7, since 2026-01-01T00:00:00+0000"


def test_release_removes_the_lock_file(tmp_path):
    path = tmp_path / ".lock"
    with FolderLock(path):
        assert path.is_file()
    assert not path.exists()                        # a finished run leaves no lock file
    with FolderLock(path) as again:                 # and the next one starts clean
        assert again.stale is None


def test_a_run_that_opened_the_file_as_its_holder_removed_it_takes_a_new_one(tmp_path, monkeypatch):
    """The race that removing lock files opens: B opens the file, A (holding it) removes it and lets
    go, B locks the removed file. B must notice and lock the file at the path instead, or a third run
    would create a new file, lock it too, and two runs would write one folder."""
    import weathergen.io.lock as lock_module

    path = tmp_path / ".lock"
    holder = FolderLock(path).acquire()
    real_open, opened = os.open, []

    def open_then_holder_finishes(name, flags, mode=0o777):
        fd = real_open(name, flags, mode)
        if not opened:
            holder.release()                        # right after B opened the holder's file
        opened.append(fd)
        return fd

    monkeypatch.setattr(lock_module.os, "open", open_then_holder_finishes)
    late = FolderLock(path).acquire()
    monkeypatch.undo()
    assert len(opened) == 2                          # it opened the file again
    assert os.fstat(late._fd).st_ino == os.stat(path).st_ino
    with pytest.raises(FolderBusy, match=f"pid {os.getpid()}"):
        FolderLock(path).acquire()                   # one lock, not two
    late.release()
