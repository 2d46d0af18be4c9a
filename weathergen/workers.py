"""Set-up of worker processes (``render --workers``): signals, death with the main process.

A worker must not outlive its main process, even one killed with ``kill -9`` while the worker is
still starting (importing torch takes seconds, a minute on a loaded machine). On Linux the kernel
sees to it: each worker is started with the parent-death signal set (``prctl(PR_SET_PDEATHSIG,
SIGKILL)``, between fork and exec, before the worker runs any Python), so it is killed the moment
the main process dies. multiprocessing's resource tracker then reads end-of-file on its pipe (the
main process and the workers held its other end), removes the semaphores the run left behind and
leaves. Elsewhere a watchdog thread that :func:`init_worker` starts polls the main process.

Kept free of heavy imports (no torch), so that a worker runs its initializer within moments.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing.util
import os
import signal
import subprocess
import sys
import threading
import time

#: How often a worker checks that its main process is alive (seconds).
WATCH_INTERVAL = 0.2


#: The signals a scheduler or a user sends to stop a run.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)

#: ``PR_SET_PDEATHSIG`` of ``<linux/prctl.h>``.
_PR_SET_PDEATHSIG = 1


def _load_prctl():
    """libc's ``prctl`` on Linux, else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong]
    prctl.restype = ctypes.c_int
    return prctl


_PRCTL = _load_prctl()

#: Whether the kernel kills the workers with the main process (else the watchdog does).
PARENT_DEATH_SIGNAL = _PRCTL is not None


class _Unwaited(subprocess.Popen):
    """A child whose exit multiprocessing waits for, by pid: never waited for here (the default
    ``__del__`` would queue it for :mod:`subprocess`'s own reaping, which could take its exit
    status from multiprocessing)."""

    def __del__(self):
        pass


def _spawn_dying_with_parent(path, args, passfds):
    """What ``multiprocessing.util.spawnv_passfds`` does (exec ``path`` with ``args``, passing the
    file descriptors ``passfds``, return the pid), with the parent-death signal set in the child
    before the exec."""
    parent = os.getpid()

    def die_with_parent():
        _PRCTL(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        if os.getppid() != parent:          # the parent died before the signal was set
            os._exit(1)

    child = _Unwaited(list(args), executable=path, pass_fds=tuple(passfds), close_fds=True,
                      restore_signals=False, preexec_fn=die_with_parent)
    return child.pid


_spawn_lock = threading.RLock()


@contextlib.contextmanager
def _dying_with_this_process():
    """Processes that multiprocessing starts in this block die with this process (Linux only).

    The kernel sends the signal when the *thread* that started the child ends: start workers from
    a thread that outlives them (the pool is shut down before the thread ends).
    """
    if _PRCTL is None:
        yield
        return
    with _spawn_lock:
        before = multiprocessing.util.spawnv_passfds
        multiprocessing.util.spawnv_passfds = _spawn_dying_with_parent
        try:
            yield
        finally:
            multiprocessing.util.spawnv_passfds = before


@contextlib.contextmanager
def spawning():
    """Start worker processes inside this block: they die with this process, and they are born
    with Ctrl-C and SIGTERM blocked.

    Death: see the module's description (the kernel's parent-death signal on Linux). Signals: a
    new process inherits the blocked set, so a group-wide signal that comes while a worker is
    still importing (before :func:`init_worker` ignores it) cannot kill it and break the pool; in
    the main process the signal is only delayed until the block ends (blocking needs the main
    thread; elsewhere only the first part applies).
    """
    with _dying_with_this_process():
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
    # On Linux the parent-death signal (see :func:`spawning`) has this in hand already; the
    # watchdog is the fallback on other systems and for workers started outside spawning().

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
            # A signal ignored when the run starts stays ignored: a shell starts a script's
            # background jobs (``cmd &``) with Ctrl-C ignored, and ``nohup`` ignores hang-ups, so
            # that those signals do not stop them; the workers ignore both anyway.
            self._previous = {s: signal.signal(s, self._hold) for s in self.SIGNALS
                              if signal.getsignal(s) != signal.SIG_IGN}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        if self.signum is not None and exc[0] is None:
            self.pass_on()

    def pass_on(self) -> None:
        """Hand the held-back signal to the handler that was in place before. The work inside the
        block was cut short, so this always raises: the handler's own exception, or
        ``KeyboardInterrupt`` when the handler returns (a run that stopped early never ends as if
        it had finished)."""
        handler = self._previous.get(self.signum)
        if callable(handler):
            handler(self.signum, None)
        elif handler == signal.SIG_DFL and self.signum != signal.SIGINT:
            signal.raise_signal(self.signum)
        raise KeyboardInterrupt


def how_it_ended(exitcode: int | None) -> str:
    """A worker process's end in words, from its exit code (negative: the signal that killed it)."""
    if exitcode is None:
        return "still running"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        if -exitcode == getattr(signal, "SIGKILL", None):
            return f"killed by {name}, as the system does when memory runs out"
        return f"killed by {name}"
    return f"exited with code {exitcode}"
