"""Helpers of the tests that run commands: waiting on a running process, the bytes of an output,
a script imported as a module."""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import sys
import time
from pathlib import Path


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
