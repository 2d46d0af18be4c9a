"""What `weathergen render` promises when things go wrong: kills, full disks, concurrent runs,
paths, bad pairs. Each test drives the failure itself on the demo scene (or a tiny fake Sintel).

docs/guarantees.md names these tests.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from weathergen.cli.main import _register, cli
from run_helpers import wait_for

# Six pairs (both demo scenes, three each) of a few hundred particles: long enough to interrupt.
SIX = ("--frames-per-scene", "3", "--set", "count=300")
TWO = ("--scenes", "street", "--frames-per-scene", "2", "--set", "count=300")
SCRIPT = Path(sys.executable).parent / "weathergen"
linux_only = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads /proc")


def run(*args):
    _register()
    return CliRunner().invoke(cli, [str(a) for a in args])


def start(*args) -> subprocess.Popen:
    """`weathergen ARGS` in its own process group (as a shell or a job scheduler starts it)."""
    return subprocess.Popen([str(SCRIPT), *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, env=os.environ, start_new_session=True)


def children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def digests(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.suffix in (".png", ".npz")}


def metadata_files(out: Path) -> list[Path]:
    return [p for p in out.rglob("*.npz") if not p.name.startswith(".")]


def temp_files(out: Path) -> list[Path]:
    return [p for p in out.rglob(".*") if p.is_file() and ".tmp" in p.name]


def manifest(out: Path) -> dict:
    return json.loads((out / "manifest.json").read_text())


@pytest.fixture(scope="module")
def clean_six(tmp_path_factory, demo_root):
    out = tmp_path_factory.mktemp("clean") / "six"
    res = run("render", "--out", out, "-q", *SIX)
    assert res.exit_code == 0, res.output
    return out


# -- kills ---------------------------------------------------------------------------------------

def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


@pytest.fixture
def busy_cpu():
    """Every core busy with a spinning process, as on a loaded machine (a child that starts up
    then waits for a core)."""
    spinners = [subprocess.Popen([sys.executable, "-S", "-c", "while True: pass"])
                for _ in range(os.cpu_count() or 2)]
    yield
    for p in spinners:
        p.kill()
        p.wait()


#: How long the workers and the resource tracker may outlive a killed main process.
ORPHAN_SECONDS = 2.0


@linux_only
@pytest.mark.slow
def test_kill_9_right_after_the_workers_start_leaves_no_orphans(tmp_path, demo_root, busy_cpu):
    """The parent dies before its workers finished starting: they and multiprocessing's resource
    tracker are gone within moments, on a busy machine too, and nothing more is written."""
    out = tmp_path / "orphans"
    proc = start("render", "--out", out, "--workers", "2", "-q", *SIX)
    # multiprocessing's resource tracker and both workers exist; the workers are still starting
    # (importing torch), long before their initializer could run
    assert wait_for(lambda: len(children(proc.pid)) >= 3), proc.communicate()[0]
    kids = children(proc.pid)
    kinds = sorted("tracker" if "resource_tracker" in cmdline(k) else "worker" for k in kids)
    assert kinds == ["tracker", "worker", "worker"], [cmdline(k) for k in kids]
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    killed = time.time()
    written = len(metadata_files(out))
    assert wait_for(lambda: not any(alive(k) for k in kids), timeout=60, every=0.02), \
        f"{[cmdline(k) for k in kids if alive(k)]} outlived their killed parent by a minute"
    lived = time.time() - killed
    assert lived < ORPHAN_SECONDS, f"the workers and the tracker outlived their parent by {lived:.1f} s"
    assert len(metadata_files(out)) == written          # and rendered nothing meanwhile


@pytest.mark.slow
def test_worker_of_a_dead_parent_leaves_and_workers_ignore_the_groups_sigterm():
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    code = ("import sys, time; from weathergen.workers import init_worker; "
            "init_worker(int(sys.argv[1])); print('ready', flush=True); time.sleep(60)")
    orphan = subprocess.Popen([sys.executable, "-c", code, str(dead.pid)], stdout=subprocess.PIPE)
    assert orphan.wait(timeout=30) == 1
    worker = subprocess.Popen([sys.executable, "-c", code, str(os.getpid())], stdout=subprocess.PIPE)
    try:
        assert worker.stdout.readline().strip() == b"ready"
        worker.send_signal(signal.SIGTERM)
        time.sleep(0.5)
        assert worker.poll() is None          # the main process decides when a worker stops
    finally:
        worker.kill()
        worker.wait()


def test_stop_requests_hold_a_signal_back_until_the_pool_is_looked_after():
    from weathergen.workers import StopRequests

    seen = []

    def cli_handler(signum, frame):
        seen.append(signum)
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, cli_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with StopRequests() as stop:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)                    # the handler runs here: it must not raise
                held = stop.signum
                assert seen == []                   # not yet passed on
        assert held == signal.SIGTERM
        assert seen == [signal.SIGTERM]             # passed on when the block ended
        assert signal.getsignal(signal.SIGTERM) is cli_handler
        with StopRequests() as stop:                # no signal: nothing passed on
            pass
        assert stop.signum is None and seen == [signal.SIGTERM]
    finally:
        signal.signal(signal.SIGTERM, previous)


@pytest.mark.slow
def test_sigterm_to_the_process_group_with_workers_stops_cleanly(tmp_path, clean_six):
    """What a job scheduler sends: every process of the group gets SIGTERM at once."""
    out = tmp_path / "term"
    proc = start("render", "--out", out, "--workers", "2", *SIX)
    assert wait_for(lambda: metadata_files(out) or proc.poll() is not None)
    os.killpg(proc.pid, signal.SIGTERM)
    output = proc.communicate(timeout=120)[0].decode()
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal arrived")
    assert proc.returncode == 128 + signal.SIGTERM, output
    assert "Traceback" not in output and "InvalidStateError" not in output, output
    assert "--resume" in output
    assert not temp_files(out)
    # the manifest lists exactly the pairs that were finished: also those the workers were
    # finishing when the signal came
    written = {k for k, p in manifest(out)["pairs"].items() if p["status"] == "written"}
    assert len(written) >= 1
    assert len(written) == len(metadata_files(out)), (written, metadata_files(out))
    res = run("render", "--out", out, "--resume", "-q", *SIX)
    assert res.exit_code == 0, res.output
    assert digests(out) == digests(clean_six)


# -- full disks and unwritable places ------------------------------------------------------------

class _FailingOs:
    """Stands in for ``os`` inside the atomic writer: ``os.replace`` fails once ``when`` says so."""

    def __init__(self, when, error):
        self.when, self.error, self.replaced = when, error, []

    def __getattr__(self, name):
        return getattr(os, name)

    def replace(self, src, dst):
        if self.when(Path(dst), self.replaced):
            raise OSError(self.error, os.strerror(self.error), str(src), None, str(dst))
        os.replace(src, dst)
        self.replaced.append(Path(dst))


def _after_first_pair(also_manifest: bool):
    def when(dst: Path, replaced: list[Path]) -> bool:
        first_done = any(p.suffix == ".npz" for p in replaced)
        return first_done and (also_manifest or dst.suffix != ".json")
    return when


@pytest.mark.parametrize("also_manifest", [False, True], ids=["pairs", "pairs-and-manifest"])
def test_full_disk_mid_run_is_one_line_and_resume_finishes(tmp_path, monkeypatch, also_manifest):
    import weathergen.io.atomic as atomic

    out = tmp_path / "full"
    failing = _FailingOs(_after_first_pair(also_manifest), errno.ENOSPC)
    monkeypatch.setattr(atomic, "os", failing)
    res = run("render", "--out", out, "-q", *TWO)
    monkeypatch.undo()
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and isinstance(res.exception, SystemExit)
    errors = [line for line in res.output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, res.output
    assert "cannot write (No space left on device)" in errors[0] and "--resume" in errors[0]
    assert ".tmp" not in errors[0]
    assert not temp_files(out)
    if also_manifest:
        assert "manifest" in errors[0]            # says that the record could not be updated
    else:
        record = manifest(out)
        assert record["summary"]["written"] == 1 and len(metadata_files(out)) == 1
    res = run("render", "--out", out, "--resume", "-q", *TWO)
    assert res.exit_code == 0, res.output
    # the pair finished before the disk filled is kept (found on disk where unrecorded)
    expected = {"written": 1, "skipped": 1} if also_manifest else {"written": 2, "skipped": 0}
    assert manifest(out)["summary"] == {**expected, "failed": 0}


def test_read_only_subfolder_names_the_file_not_a_temporary(tmp_path, monkeypatch):
    import weathergen.io.atomic as atomic

    out = tmp_path / "ro"
    failing = _FailingOs(lambda dst, done: "street_0002" in str(dst), errno.EACCES)
    monkeypatch.setattr(atomic, "os", failing)
    res = run("render", "--out", out, "-q", *TWO)
    monkeypatch.undo()
    assert res.exit_code == 2, res.output
    line = [line for line in res.output.splitlines() if line.startswith("Error:")][0]
    assert "street_0002/frame_0002" in line and "cannot write (Permission denied)" in line
    assert ".tmp" not in line and "room" not in line
    assert manifest(out)["summary"]["written"] == 1


# -- one writer per output folder ----------------------------------------------------------------

@pytest.mark.slow
def test_a_second_writer_is_refused_while_a_run_holds_the_folder(tmp_path, clean_six):
    out = tmp_path / "busy"
    first = start("render", "--out", out, "-q", *SIX)
    assert wait_for(lambda: metadata_files(out) or first.poll() is not None)
    if first.poll() is not None:
        pytest.skip("the first run finished before the second started")
    second = run("render", "--out", out, "--resume", "-q", *SIX)
    still_running = first.poll() is None
    output = first.communicate(timeout=300)[0].decode()
    assert first.returncode == 0, output
    if not still_running:
        pytest.skip("the first run finished while the second started")
    assert second.exit_code == 2, second.output
    assert f"pid {first.pid} on {socket.gethostname()}" in second.output
    assert "Traceback" not in second.output
    # the refused run changed nothing: one run in the record, the same bytes as a clean run
    assert len(manifest(out)["runs"]) == 1
    assert digests(out) == digests(clean_six)


@pytest.mark.slow
def test_stale_lock_of_a_killed_run_is_reported_and_taken_over(tmp_path):
    out = tmp_path / "stale"
    proc = start("render", "--out", out, "-q", *TWO)
    assert wait_for(lambda: (out / "manifest.d").is_dir() or proc.poll() is not None)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    res = run("render", "--out", out, "--resume", "-q", *TWO)
    assert res.exit_code == 0, res.output
    assert f"stale lock of pid {proc.pid} on {socket.gethostname()}" in res.output


def test_a_finished_render_leaves_no_lock_file(tmp_path, clean_six):
    assert not list(clean_six.rglob(".weathergen-lock*"))
    out = tmp_path / "shards"                      # each shard's own lock file goes too
    for shard in ("1/2", "2/2"):
        assert run("render", "--out", out, "--shard", shard, "-q", *TWO).exit_code == 0
    assert not list(out.rglob(".weathergen-lock*"))


def test_resume_of_one_shard_spares_the_temporary_files_of_another(tmp_path):
    out = tmp_path / "shards"
    assert run("render", "--out", out, "--shard", "1/2", "-q", *TWO).exit_code == 0
    mine = out / "training/snow_clean/street_0001/.frame_0001.png.x1.tmp"
    theirs = out / "training/snow_clean/street_0002/.frame_0002.png.x2.tmp"   # shard 2, running
    theirs.parent.mkdir(parents=True, exist_ok=True)
    mine.write_bytes(b"killed")
    theirs.write_bytes(b"in progress")
    res = run("render", "--out", out, "--shard", "1/2", "--resume", "-q", *TWO)
    assert res.exit_code == 0, res.output
    assert not mine.exists() and theirs.exists()


# -- paths ---------------------------------------------------------------------------------------

def test_relative_root_works_from_anywhere(tmp_path, monkeypatch, fake_sintel):
    monkeypatch.chdir(fake_sintel.parent)
    res = run("render", "--root", fake_sintel.name, "--out", "out", "--set", "count=20", "-q")
    assert res.exit_code == 0, res.output
    recorded = manifest(fake_sintel.parent / "out")["input"]["root"]
    assert recorded == str(fake_sintel) and Path(recorded).is_absolute()
    # the same root written as an absolute path is the same setting
    res = run("render", "--root", fake_sintel, "--out", "out", "--set", "count=20", "--resume", "-q")
    assert res.exit_code == 0, res.output
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    res = run("preview", fake_sintel.parent / "out", "--out", "sheet.png", "--width", "64")
    assert res.exit_code == 0, res.output
    assert (elsewhere / "sheet.png").is_file()


# -- bad pairs -----------------------------------------------------------------------------------

def test_every_pair_unreadable_exits_2_and_writes_nothing(tmp_path, fake_sintel):
    for depth in (fake_sintel / "training/depth").rglob("*.dpt"):
        depth.write_bytes(b"junk")
    out = tmp_path / "out"
    res = run("render", "--root", fake_sintel, "--out", out, "--set", "count=20", "-q")
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    assert "every selected pair failed" in res.output
    assert not out.exists()


# -- workers -------------------------------------------------------------------------------------

def test_auto_workers_use_the_cores_only_when_there_is_enough_to_do():
    from weathergen.render.plan import auto_workers

    assert auto_workers(6, "cpu", cores=2) == 1            # the demo scene: one process
    assert auto_workers(1041, "cpu", cores=2) == 2         # Sintel training: every core
    assert auto_workers(20, "cpu", cores=16) == 2          # a worker per 8 pairs at most
    assert auto_workers(1041, "cuda", cores=16) == 1       # one process feeds the GPU
    res = run("render", "--help")
    assert "auto" in res.output and "one per core" in " ".join(res.output.split())
    res = run("render", "--workers", "0", "--out", "x")
    assert res.exit_code == 2 and "at least 1" in res.output
