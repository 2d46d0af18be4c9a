"""Set-up of worker processes (``render --workers``): signals and a watchdog on the main process.

Kept free of heavy imports (no torch), so that a worker runs it within moments of starting: a
worker whose main process dies while the worker is still starting must notice and leave, not
import torch for seconds first and then wait for work forever.
"""

from __future__ import annotations

import os
import signal
import threading
import time

#: How often a worker checks that its main process is alive (seconds).
WATCH_INTERVAL = 0.2


def init_worker(parent: int) -> None:
    """Initializer of a worker process; ``parent`` is the main process's pid, passed by it.

    (Read in the worker with ``os.getppid()``, it would be the pid of whatever adopted the worker
    when the main process died while the worker was starting, and the watchdog would never fire.)
    """
    # Ctrl-C and a scheduler's SIGTERM reach the whole process group; the main process alone
    # decides what stops, and lets the pairs in progress finish, so that no worker is cut off in
    # the middle of a pair (and the pool never breaks under the main process's feet).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if os.getppid() != parent:
        os._exit(1)

    def watch():
        while os.getppid() == parent:
            time.sleep(WATCH_INTERVAL)
        os._exit(1)             # the main process is gone: no one will collect what we render

    threading.Thread(target=watch, name="weathergen-watchdog", daemon=True).start()
