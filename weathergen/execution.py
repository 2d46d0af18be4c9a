"""Where the pairs of a run are computed, and the accounting of it.

Two executors run the work units (a batch of pairs) of ``render`` and ``attack``:

- ``local``: this process (``render`` may add its own process pool, ``--workers``);
- ``ray``: each unit is a Ray task on a Ray cluster (``--executor ray --ray-address auto``).
  A task that dies with its worker (a killed process, a lost node) is retried by Ray
  (:data:`RAY_MAX_RETRIES`); every output file is written atomically, so a retried pair is never
  found half-written. The driver alone writes the manifest.

Ray is an optional dependency (``pip install 'weathergen[ray]'``); nothing here imports it before
it is asked for. The output folder must be one that every node of the cluster sees at the same
path (a shared file system), as do the dataset and the checkpoint.

Accounting: :func:`where_ran` says which host, process, Ray worker and device computed a pair;
:class:`RunClock` turns pairs done into a rate and an estimated finish.
"""

from __future__ import annotations

import os
import socket
import sys
import time
from datetime import datetime, timedelta, timezone
from typing import Callable, Iterator, Optional, Sequence

from .errors import ConfigError
from .words import counted

EXECUTORS = ("local", "ray")

#: How often Ray reruns a task whose worker died (the pair's outputs are written atomically).
RAY_MAX_RETRIES = 3

RAY_INSTALL_HINT = "pip install 'weathergen[ray]'"


def check_executor(executor: str) -> str:
    """The executor's name, or a ConfigError; ``ray`` also needs Ray to be importable."""
    if executor not in EXECUTORS:
        raise ConfigError(f"${{executor}} {executor!r}: choose one of {', '.join(EXECUTORS)}")
    if executor == "ray":
        _import_ray()
    return executor


def _import_ray():
    try:
        import ray
    except ImportError:
        raise ConfigError(f"${{executor}} ray needs Ray, which is not installed: "
                          f"{RAY_INSTALL_HINT}") from None
    return ray


def connect_ray(address: Optional[str] = "auto"):
    """Join the Ray cluster at ``address`` (``auto``: the one started on this machine with
    ``ray start``; ``local``: start a private one for this run), unless this process is already
    connected. Returns the ``ray`` module."""
    ray = _import_ray()
    if ray.is_initialized():
        return ray
    kwargs = {"include_dashboard": False, "log_to_driver": False}
    try:
        if address in (None, "local"):
            ray.init(**kwargs)
        else:
            ray.init(address=address, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ConfigError(f"${{ray_address}} {address}: cannot join a Ray cluster ({first}); "
                          f"start one with `ray start --head` or use ${{ray_address}} local"
                          ) from None
    return ray


def _call(fn, args):
    return fn(*args)


def ray_map(fn: Callable, units: Sequence[tuple], *, address: Optional[str] = "auto",
            num_gpus: float = 0, num_cpus: float = 1, max_retries: int = RAY_MAX_RETRIES,
            in_flight: Optional[int] = None) -> Iterator:
    """Run ``fn(*unit)`` for every unit as a Ray task; yield the results as they complete.

    ``fn`` must be importable by the workers (a module-level function of this package). At most
    ``in_flight`` tasks are submitted at a time (default: twice the cluster's CPUs), so an
    interrupted driver leaves little work behind. Interrupting the generator cancels the tasks
    that have not finished.
    """
    ray = connect_ray(address)
    remote = ray.remote(num_cpus=num_cpus, num_gpus=num_gpus, max_retries=max_retries)(_call)
    if in_flight is None:
        in_flight = max(2, 2 * int(ray.cluster_resources().get("CPU", 1)))
    queue = list(units)
    pending: list = []
    try:
        while queue or pending:
            while queue and len(pending) < in_flight:
                pending.append(remote.remote(fn, queue.pop(0)))
            done, pending = ray.wait(pending, num_returns=1)
            for ref in done:
                yield ray.get(ref)
    finally:
        for ref in pending:
            ray.cancel(ref)


def ray_gpus_for(device: str) -> int:
    """GPUs a Ray task claims for ``device``: one for a CUDA device, none for the CPU."""
    return 1 if str(device).startswith("cuda") else 0


def worker_device(device: str, executor: str) -> str:
    """The device a unit uses where it runs: a Ray task sees only the GPU it claimed, as
    ``cuda``."""
    return "cuda" if executor == "ray" and str(device).startswith("cuda") else str(device)


def where_ran(device) -> dict:
    """The host, process, Ray worker (None outside Ray) and device that computed a pair."""
    worker = None
    ray = sys.modules.get("ray")               # only where the run imported it
    if ray is not None and ray.is_initialized():
        try:
            ctx = ray.get_runtime_context()
            if ctx.worker.mode == ray.WORKER_MODE:
                worker = ctx.get_worker_id()
        except Exception:                      # accounting never fails a pair
            worker = None
    return {"host": socket.gethostname(), "pid": os.getpid(), "worker": worker,
            "device": str(device)}


class RunClock:
    """Progress of a run: pairs done (of ``total``), pairs per hour and the estimated finish.

    Only pairs computed here count in the rate: those an earlier run finished (skipped) and those
    that failed (an unreadable pair fails in moments) count as done, not as the pace of the run.
    """

    def __init__(self, total: int, now: Callable[[], float] = time.monotonic):
        self.total, self.now = total, now
        self.start = now()
        self.done = 0
        self.computed = 0

    def add(self, computed: bool = True) -> None:
        """One more pair done; ``computed``: written by this run (not skipped, not failed)."""
        self.done += 1
        self.computed += int(computed)

    def pace(self) -> str:
        """The rate for a progress bar: ``"2.50 pairs/s"``, ``"12.0 s/pair"``, or ``""`` before
        the first computed pair."""
        rate = self.per_hour()
        if rate is None:
            return ""
        per_second = rate / 3600.0
        return f"{per_second:.2f} pairs/s" if per_second >= 1 else f"{1 / per_second:.1f} s/pair"

    def per_hour(self) -> Optional[float]:
        elapsed = self.now() - self.start
        if self.computed == 0 or elapsed <= 0:
            return None
        return self.computed * 3600.0 / elapsed

    def remaining_seconds(self) -> Optional[float]:
        rate = self.per_hour()
        if rate is None:
            return None
        return (self.total - self.done) * 3600.0 / rate

    def time_left(self) -> str:
        """The estimated time to finish, ``"56 min"``, or ``""`` before the first computed pair."""
        left = self.remaining_seconds()
        return "" if left is None else _duration(left)

    def describe(self) -> str:
        """E.g. ``12/40 pairs, 30.0 pairs/h, finish ~ 21:56 UTC (56 min)``."""
        text = f"{self.done}/{counted(self.total, 'pair')}"
        rate, left = self.per_hour(), self.remaining_seconds()
        if rate is not None:
            text += f", {rate:.1f} pairs/h"
            finish = datetime.now(timezone.utc) + timedelta(seconds=left)
            text += f", finish ~ {finish:%H:%M} UTC ({_duration(left)})"
        return text


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


__all__ = ["EXECUTORS", "RAY_MAX_RETRIES", "RunClock", "check_executor", "connect_ray",
           "ray_gpus_for", "ray_map", "where_ran", "worker_device"]
