"""Helpers of the tests that run commands: a command run in this process and its one-line error,
waiting on a running process, the bytes of an output, a script imported as a module."""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import sys
import time
from pathlib import Path

from click.testing import CliRunner

from weathergen.cli.main import _register, cli


def cli_run(*args):
    """``weathergen ARGS`` run in this process (click's runner), every command registered."""
    _register()
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_line_error(res, code: int = 2) -> str:
    """The run ended with ``code`` and a single 'Error: ...' line, no traceback; that line."""
    assert res.exit_code == code, res.output
    assert isinstance(res.exception, SystemExit), repr(res.exception)
    assert "Traceback" not in res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), res.output
    return lines[0]


def wait_for(condition, timeout: float = 180.0, every: float = 0.01) -> bool:
    """Whether ``condition()`` became true within ``timeout`` seconds, asked every ``every``."""
    deadline = time.time() + timeout
    while time.time() < deadline:
        if condition():
            return True
        time.sleep(every)
    return False


def output_digests(root: Path) -> dict:
    """sha256 of every file of an output but its manifest and hidden files, by relative path."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and "manifest" not in str(p)
            and not p.name.startswith(".")}


@contextlib.contextmanager
def script_module(path: Path):
    """The script at ``path`` imported as a module named after its file, registered in
    ``sys.modules`` while the block runs (dataclasses look their module up there)."""
    name = path.stem
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[name]
