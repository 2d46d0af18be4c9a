"""Ctrl-C while the command line starts: one line and exit code 130, not a traceback.

Importing the commands imports torch, which takes seconds (a minute on a loaded machine); a
Ctrl-C then would raise ``KeyboardInterrupt`` deep inside ``import torch``. :mod:`weathergen.cli.main`
imports this module before anything heavy: from then until :func:`started`, Ctrl-C prints
:data:`MESSAGE` and ends the process at once (nothing has been written yet). A Ctrl-C that the
shell told the process to ignore stays ignored, and so does one in a process that set its own
handler (a program importing the command line as a library).
"""

from __future__ import annotations

import os
import signal
import threading

#: What Ctrl-C during start-up prints.
MESSAGE = "Interrupted while starting; nothing was done.\n"


def _interrupted(signum, frame):
    os.write(2, MESSAGE.encode())
    os._exit(128 + signum)


def _guard():
    """Install the start-up handler where Python's own is in place; return what to restore."""
    if threading.current_thread() is not threading.main_thread():
        return None
    if signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return None
    return signal.signal(signal.SIGINT, _interrupted)


_before = _guard()


def started() -> None:
    """Start-up is over: Ctrl-C raises ``KeyboardInterrupt`` again, which the commands handle."""
    global _before
    if _before is not None and signal.getsignal(signal.SIGINT) is _interrupted:
        signal.signal(signal.SIGINT, _before)
    _before = None
