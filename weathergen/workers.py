"""Set-up of worker processes (``render --workers``): signals and a watchdog on the main process.

Kept free of heavy imports (no torch), so that a worker runs it within moments of starting: a
worker whose main process dies while the worker is still starting must notice and leave, not
import torch for seconds first and then wait for work forever.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time

#: How often a worker checks that its main process is alive (seconds).
WATCH_INTERVAL = 0.2


#: The signals a scheduler or a user sends to stop a run.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def spawning():
    """Block Ctrl-C and SIGTERM in the calling thread while it starts worker processes.

    A new process inherits the blocked set, so a group-wide signal that comes while a worker is
    still importing (before :func:`init_worker` ignores it) cannot kill it and break the pool; in
    the main process the signal is only delayed until the block ends.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def init_worker(parent: int) -> None:
    """Initializer of a worker process; ``parent`` is the main process's pid, passed by it.

    (Read in the worker with ``os.getppid()``, it would be the pid of whatever adopted the worker
    when the main process died while the worker was starting, and the watchdog would never fire.)
    """
    # Ctrl-C and a scheduler's SIGTERM reach the whole process group; the main process alone
    # decides what stops, and lets the pairs in progress finish, so that no worker is cut off in
    # the middle of a pair (and the pool never breaks under the main process's feet).
    # The worker was born with both signals blocked (see :func:`spawning`), so one sent while it
    # was still starting waits; ignored from now on, it is dropped when they are unblocked.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    if os.getppid() != parent:
        os._exit(1)

    def watch():
        while os.getppid() == parent:
            time.sleep(WATCH_INTERVAL)
        os._exit(1)             # the main process is gone: no one will collect what we render

    threading.Thread(target=watch, name="weathergen-watchdog", daemon=True).start()


class StopRequests:
    """Ctrl-C and SIGTERM, held back while a pool of workers is being looked after.

    Inside ``with StopRequests() as stop:`` (main thread only) the two signals no longer raise
    wherever the main process happens to be (between handing out a chunk and remembering it, say),
    they set ``stop.signum``; the loop polls it, lets the running work finish and records it. On
    leaving, the handlers that were in place come back, and a held-back signal is passed on to
    them (the CLI's turns SIGTERM into an interruption, Python's turns SIGINT into
    ``KeyboardInterrupt``). Outside the main thread signals cannot be handled, and nothing changes.
    """

    SIGNALS = STOP_SIGNALS

    def __init__(self):
        self.signum: int | None = None
        self._previous: dict = {}

    def _hold(self, signum, frame):
        if self.signum is None:
            self.signum = signum

    def __enter__(self) -> "StopRequests":
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._hold) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        if self.signum is not None and exc[0] is None:
            self.pass_on()

    def pass_on(self) -> None:
        """Hand the held-back signal to the handler that was in place before (which may raise)."""
        handler = self._previous.get(self.signum)
        if callable(handler):
            handler(self.signum, None)
        elif handler == signal.SIG_DFL:
            if self.signum == signal.SIGINT:
                raise KeyboardInterrupt
            signal.raise_signal(self.signum)
