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
