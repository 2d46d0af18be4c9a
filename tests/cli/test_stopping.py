"""`weathergen attack` and `weathergen benchmark` stop as `render` does (see
tests/render/test_render_guarantees.py): Ctrl-C and SIGTERM give exit 130 and 143, one line saying
how many pairs were finished and how to go on, and the folder's lock released; a killed run's stale
lock is taken over with a note naming its pid; no lock file is left when a run ends.

Each test runs the real command in its own process on the demo scene, with RAFT-small (the released
weights shipped with the package), one refinement iteration and one step, and drives the signal itself.
docs/guarantees.md names these tests.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from weathergen.cli.main import cli
from run_helpers import wait_for

pytestmark = pytest.mark.slow

SCRIPT = Path(sys.executable).parent / "weathergen"
#: Six pairs (both demo scenes, three each), each a few seconds: long enough to interrupt.
SIX = ("--frames-per-scene", "3", "--set", "count=100")
#: One pair: a run to kill once it holds its folder.
ONE = ("--scenes", "courtyard", "--frames-per-scene", "1", "--set", "count=100")


def attack_args(weights, out, *extra):
    return ["attack", "--model", "raft-small", "--checkpoint", weights, "--iters", "1",
            "--steps", "1", "--out", out, "-q", *extra]


def benchmark_args(weights, out, *extra):
    return ["benchmark", "--networks", "raft-small", "--checkpoint", f"raft-small={weights}",
            "--presets", "snow", "--lp", "", "--steps", "1", "--iters", "1", "--out", out,
            "--quiet", *extra]


def start(args) -> subprocess.Popen:
    """`weathergen ARGS` in its own process group, with Ctrl-C at its default (a shell may start
    us with it ignored, which the child would inherit)."""
    return subprocess.Popen([str(SCRIPT), *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, env=os.environ, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def invoke(args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def written_pairs(folder: Path) -> int:
    """Pairs an attack folder's manifest records as written (0 before it has one)."""
    try:
        pairs = json.loads((folder / "manifest.json").read_text())["pairs"]
    except (OSError, ValueError, KeyError):
        return 0
    return sum(p["status"] == "written" for p in pairs.values())


def lock_files(root: Path) -> list[Path]:
    return sorted(root.rglob(".weathergen-lock*"))


def stopped_line(output: str) -> int:
    """N of the "Interrupted after N pairs; ..." line (the only line of the output)."""
    lines = output.strip().splitlines()
    assert len(lines) == 1, output
    match = re.fullmatch(r"Interrupted after (\d+) pairs?; (rerun with --resume|rerun the same "
                         r"command) to finish \(finished pairs are kept\)\.", lines[0])
    assert match, output
    return int(match.group(1))


def assert_released(folder: Path) -> None:
    """The lock is free and was let go of cleanly: no file left, nobody recorded in it."""
    from weathergen.io.lock import FolderLock

    assert not lock_files(folder)
    with FolderLock(folder / ".weathergen-lock") as lock:
        assert lock.stale is None


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_attack_stops_like_render(tmp_path, demo_root, raft_small_weights, signum):
    out = tmp_path / "attack"
    proc = start(attack_args(raft_small_weights, out, *SIX))
    assert wait_for(lambda: written_pairs(out) >= 1 or proc.poll() is not None)
    proc.send_signal(signum)
    output = proc.communicate(timeout=120)[0].decode()
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal arrived")
    assert proc.returncode == 128 + signum, output
    assert "Traceback" not in output
    assert stopped_line(output) == written_pairs(out) >= 1    # as the manifest records them
    assert "--resume" in output
    assert not [p for p in out.rglob(".*") if ".tmp" in p.name]
    assert_released(out)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_benchmark_stops_like_render(tmp_path, demo_root, raft_small_weights, signum):
    out = tmp_path / "bench"
    cell = out / "runs" / "raft-small" / "snow"
    proc = start(benchmark_args(raft_small_weights, out, *SIX))
    assert wait_for(lambda: written_pairs(cell) >= 1 or proc.poll() is not None)
    proc.send_signal(signum)
    output = proc.communicate(timeout=120)[0].decode()
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal arrived")
    assert proc.returncode == 128 + signum, output
    assert "Traceback" not in output
    assert stopped_line(output) == written_pairs(cell) >= 1
    assert "rerun the same command" in output                 # it resumes by itself
    assert_released(cell)


def test_stale_lock_of_a_killed_attack_is_reported_and_taken_over(tmp_path, demo_root,
                                                                  raft_small_weights):
    out = tmp_path / "killed"
    args = attack_args(raft_small_weights, out, *ONE)
    proc = start(args)
    # the folder is claimed (its lock taken) once the network is loaded
    assert wait_for(lambda: (out / ".weathergen-attack").exists() or proc.poll() is not None)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    if not lock_files(out):
        pytest.skip("the run finished before it was killed")
    resumed = invoke([*args, "--resume"])
    assert resumed.exit_code == 0, resumed.output
    notes = [line for line in resumed.output.splitlines() if line.startswith("Note:")]
    assert len(notes) == 1, resumed.output
    assert f"took over the stale lock of pid {proc.pid} on {socket.gethostname()}" in notes[0]
    assert not lock_files(out)


def test_stale_lock_of_a_killed_benchmark_is_reported_and_taken_over(tmp_path, demo_root,
                                                                     raft_small_weights):
    out = tmp_path / "killed"
    cell = out / "runs" / "raft-small" / "snow"
    args = benchmark_args(raft_small_weights, out, *ONE)
    proc = start(args)
    assert wait_for(lambda: (cell / ".weathergen-attack").exists() or proc.poll() is not None)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    if not lock_files(out):
        pytest.skip("the run finished before it was killed")
    again = invoke(args)
    assert again.exit_code == 0, again.output
    notes = [line for line in again.output.splitlines() if line.startswith("Note:")]
    assert len(notes) == 1, again.output
    assert f"took over the stale lock of pid {proc.pid} on {socket.gethostname()}" in notes[0]
    assert not lock_files(out)


def test_a_benchmark_stopped_while_writing_its_tables_stops_the_same_way(tmp_path, monkeypatch):
    """The tables are the last part of a benchmark run: Ctrl-C there is the same one line and
    exit 130, not a traceback (the table files are written atomically, so none is half-written)."""
    import weathergen.cli.benchmark as command

    def interrupted(spec):
        raise KeyboardInterrupt

    monkeypatch.setattr(command, "run_grid", lambda *args, **kwargs: [])
    monkeypatch.setattr(command, "write_tables", interrupted)
    result = CliRunner().invoke(cli, ["benchmark", "--networks", "raft-small", "--presets", "snow",
                                      "--lp", "", "--out", str(tmp_path / "b"), "-q"])
    assert result.exit_code == 130, result.output
    assert stopped_line(result.output) == 0
