"""How the commands that run jobs stop on Ctrl-C or SIGTERM: cleanly, in one line, with the
signal's exit code (130, 143).

The job itself records what it finished and releases its folder as the interruption passes
through it (``KeyboardInterrupt``); here SIGTERM is made to pass the same way, and the command
says how far it got.
"""

from __future__ import annotations

import contextlib
import signal
import sys
from typing import Iterator, NoReturn

import click

from weathergen.words import counted


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[list]:
    """Treat SIGTERM (``kill``, a cluster's time limit) like Ctrl-C for the block.

    Either way the run stops cleanly: the pairs in progress finish or leave no file, the manifest
    records what was written, the lock is released, and ``--resume`` finishes the job. Yields a list
    that receives the number of the signal that stopped the run. The ``SystemError`` that an
    interruption can cause (see :func:`interruption`) leaves the block as ``KeyboardInterrupt``.
    A SIGTERM that the process was started ignoring stays ignored.
    """
    stopped_by: list = []

    def handler(signum, frame):
        stopped_by.append(signum)
        raise KeyboardInterrupt

    previous = None
    if signal.getsignal(signal.SIGTERM) != signal.SIG_IGN:
        with contextlib.suppress(ValueError):      # not the main thread: leave signals alone
            previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield stopped_by
    except SystemError as exc:
        if interruption(exc):
            raise KeyboardInterrupt from None
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def interruption(exc: BaseException) -> bool:
    """Whether ``exc`` is an interruption: a ``KeyboardInterrupt``, or an error it caused (a
    Ctrl-C inside some C calls surfaces as ``SystemError`` "returned a result with an exception
    set", the ``KeyboardInterrupt`` its cause)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def exit_interrupted(written: int, stopped_by: list, again: str = "rerun with --resume") -> NoReturn:
    """Say how many pairs this run finished and how to go on; exit with 128 + the signal's number
    (130 for Ctrl-C, 143 for SIGTERM)."""
    click.echo(f"Interrupted after {counted(written, 'pair')}; {again} to finish (finished pairs are kept).",
               err=True)
    sys.exit(128 + (stopped_by[0] if stopped_by else signal.SIGINT))
