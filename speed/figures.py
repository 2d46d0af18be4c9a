"""The figures file: what the benchmarks measured, on which tree and which machine.

Every CPU figure the documentation gives for speed or memory lives here and nowhere else:
``docs/figures/bench.json`` (one section per benchmark command) and ``docs/figures/bench.md``
(the same, for reading; rewritten from the JSON each time). ``make bench`` fills both. The GPU
figures have their page beside it, ``docs/figures/gpu.md``, written by :mod:`gpu_figures` from
the JSON files of ``make gpu-check`` and of the GPU session. A script
runs its main through :func:`record`::

    if __name__ == "__main__":
        sys.exit(record(main))

which prints as before and, when the run succeeds, stores what it printed as the section of its
command line (``python speed/bench.py``, with its arguments) together with the tree (git
commit, and whether it had uncommitted changes), the machine (CPU model, cores, memory, torch
version, GPU), the benchmark settings in the environment (``BENCH_*``) and the load average
when it started. A rerun of one command replaces its section and keeps the others, so each
section says for itself where and on what it was measured.

``BENCH_FIGURES=PATH`` records into ``PATH`` (its ``.md`` beside it) instead;
``BENCH_FIGURES=none`` only prints. Internal worker runs (``--worker``, ``--one``: a script
running one measurement for its parent) are never recorded.
"""

from __future__ import annotations

import io
import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable, Optional

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "docs" / "figures" / "bench.json"
#: Arguments with which a script measures one thing for its parent process.
WORKER_FLAGS = ("--worker", "--one")
#: The order of sections in bench.md: make bench's order; other commands follow, sorted.
ORDER = ("bench.py", "bench_fog.py", "bench_core.py", "bench_field.py", "bench_combined.py",
         "bench_atmosphere.py", "bench_models.py", "bench_attack.py", "bench_training.py", "bench_batch.py",
         "bench_quick_look.py")


def figures_path() -> Optional[Path]:
    """Where :func:`record` writes (``BENCH_FIGURES``, default docs/figures/bench.json), or None."""
    value = os.environ.get("BENCH_FIGURES")
    if value is None:
        return DEFAULT
    return None if value.strip().lower() in ("", "none") else Path(value)


def command_line(argv: Optional[list[str]] = None) -> str:
    """The section's name: ``python speed/SCRIPT ARGS`` for the running script
    (``scripts/SCRIPT`` for one of the comparison scripts there)."""
    argv = list(sys.argv if argv is None else argv)
    folder = "scripts" if Path(argv[0]).parent.name == "scripts" else "speed"
    return shlex.join(["python", f"{folder}/{Path(argv[0]).name}", *argv[1:]])


def tree() -> dict:
    """The git commit of the checkout and whether it has uncommitted changes (None outside git)."""
    def git(*args: str) -> Optional[str]:
        try:
            done = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True,
                                  timeout=30)
        except (OSError, subprocess.SubprocessError):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    status = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": commit, "dirty": bool(status) if status is not None else None}


def machine() -> dict:
    """CPU model, cores, memory, operating system, Python and torch, and the GPU if there is one."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    memory = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                memory = round(int(line.split()[1]) / 2 ** 20, 1)
    except OSError:
        pass
    info = {"cpu": cpu, "cores": os.cpu_count(), "memory_gib": memory,
            "system": f"{platform.system()} {platform.release()}",
            "python": platform.python_version()}
    try:
        import torch

        info["torch"] = torch.__version__
        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    except ImportError:
        info["torch"] = None
    return info


def load_average() -> Optional[list[float]]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


class _Tee(io.TextIOBase):
    """Writes to the real stdout and keeps a copy."""

    def __init__(self, stream):
        self.stream, self.copy = stream, io.StringIO()

    def write(self, text: str) -> int:
        self.copy.write(text)
        return self.stream.write(text)

    def flush(self) -> None:
        self.stream.flush()


def record(main: Callable[[], Optional[int]], argv: Optional[list[str]] = None) -> Optional[int]:
    """Run ``main()`` (printing as usual); when it returns None or 0, store what it printed in
    the figures file as the section of this command line. Returns what ``main`` returned."""
    argv = list(sys.argv if argv is None else argv)
    path = figures_path()
    if path is None or any(flag in argv[1:] for flag in WORKER_FLAGS):
        return main()
    started, load, start = time.strftime("%Y-%m-%d %H:%M:%S %z"), load_average(), time.perf_counter()
    tee = _Tee(sys.stdout)
    sys.stdout = tee
    try:
        result = main()
    finally:
        sys.stdout = tee.stream
    if result not in (None, 0):
        return result
    section = {"command": command_line(argv), **tree(), "started": started,
               "seconds": round(time.perf_counter() - start, 1), "load_average": load,
               "machine": machine(),
               "settings": {k: v for k, v in sorted(os.environ.items()) if k.startswith("BENCH_")
                            and k != "BENCH_FIGURES"},
               "output": tee.copy.getvalue()}
    write_section(path, section)
    print(f"(recorded in {_shown(path)} and {_shown(path.with_suffix('.md'))})")
    return result


def _shown(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def read_figures(path: Path = DEFAULT) -> dict:
    """The figures file's content: ``{"sections": {command: section}}`` (empty when missing)."""
    if not path.exists():
        return {"sections": {}}
    return json.loads(path.read_text())


def write_section(path: Path, section: dict) -> None:
    """Replace (or add) one section of the figures file and rewrite its Markdown page."""
    data = read_figures(path)
    data["sections"][section["command"]] = section
    data["sections"] = dict(sorted(data["sections"].items(), key=lambda item: _rank(item[0])))
    path.parent.mkdir(parents=True, exist_ok=True)
    for target, text in ((path, json.dumps(data, indent=1, ensure_ascii=False) + "\n"),
                         (path.with_suffix(".md"), markdown(data))):
        tmp = target.with_name(f".{target.name}.tmp")
        tmp.write_text(text)
        os.replace(tmp, target)


def _rank(command: str) -> tuple:
    script = shlex.split(command)[1].rsplit("/", 1)[-1]
    return (ORDER.index(script) if script in ORDER else len(ORDER), command)


def markdown(data: dict) -> str:
    """The figures page: one section per command, with its tree, machine and printed output."""
    lines = ["# Benchmark figures", "",
             "Written by `make bench` (each script through `speed/figures.py`); do not edit by "
             "hand. Every CPU speed and memory figure of the documentation is here; each section says "
             "on which tree and machine it was measured. GPU figures: [gpu.md](gpu.md) "
             "(`make gpu-check` and `speed/gpu_session.sh`, written by `speed/gpu_figures.py`).",
             ""]
    for command, s in data["sections"].items():
        m = s["machine"]
        state = " with uncommitted changes" if s.get("dirty") else ""
        gpu = f", {m['gpu']}" if m.get("gpu") else ""
        settings = ", ".join(f"{k}={v}" for k, v in s.get("settings", {}).items()) or "defaults"
        load = s.get("load_average")
        lines += [f"## `{command}`", "",
                  f"- tree: `{(s.get('commit') or 'unknown')[:12]}`{state}, run {s['started']}, "
                  f"{s['seconds']} s",
                  f"- machine: {m['cpu']}, {m['cores']} cores, {m.get('memory_gib')} GiB{gpu}; "
                  f"{m['system']}, Python {m['python']}, torch {m.get('torch')}",
                  f"- settings: {settings}; load average at the start "
                  f"{' / '.join(map(str, load)) if load else 'unknown'}", "",
                  "```text", s["output"].rstrip("\n"), "```", ""]
    return "\n".join(lines)
