"""The last silent exits and tracebacks that a trial of bad inputs and signals found: each case now
ends with one line and its documented exit code, no traceback, no partial file under a final name,
and a manifest true to what is on disk. One test (or a few) per case, in the order of the trial's
table; the signals are sent to real processes. docs/guarantees.md names these tests.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from weathergen.cli.main import cli
from run_helpers import wait_for

SCRIPT = Path(sys.executable).parent / "weathergen"
#: Four pairs (both demo scenes, two each) of a few hundred particles: long enough to signal.
FOUR = ("--frames-per-scene", "2", "--set", "count=300")
linux_only = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="reads /proc")


def run(*args, env=None):
    return CliRunner().invoke(cli, [str(a) for a in args], env=env)


def start(*args, sigint=signal.SIG_DFL) -> subprocess.Popen:
    """`weathergen ARGS` in its own process group, Ctrl-C at ``sigint`` (a script's ``cmd &``
    starts it ignored)."""
    return subprocess.Popen([str(SCRIPT), *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, env=os.environ, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, sigint))


def metadata_files(out: Path) -> list[Path]:
    return [p for p in out.rglob("*.npz") if not p.name.startswith(".")]


def temp_files(out: Path) -> list[Path]:
    return [p for p in out.rglob(".*") if p.is_file() and p.name.count(".") > 2]


def recorded(out: Path) -> dict:
    """pair key -> status, as the manifest records them."""
    pairs = json.loads((out / "manifest.json").read_text())["pairs"]
    return {key: p["status"] for key, p in pairs.items()}


def workers_of(pid: int) -> list[int]:
    """The worker processes of a run (its children but multiprocessing's resource tracker)."""
    try:
        kids = [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []
    return [k for k in kids if b"resource_tracker" not in _cmdline(k)]


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return b""


@pytest.fixture(scope="module")
def two_pairs(tmp_path_factory, demo_root) -> Path:
    """A finished render of two demo pairs (one per scene), to preview."""
    out = tmp_path_factory.mktemp("two") / "out"
    res = run("render", "--frames-per-scene", "1", "--set", "count=100", "--out", out, "-q")
    assert res.exit_code == 0, res.output
    return out


# -- 1: Ctrl-C to the group of a run whose parent ignores it ------------------------------------

@pytest.mark.slow
def test_ctrl_c_to_the_group_of_a_run_started_ignoring_it_is_ignored_with_workers_too(tmp_path,
                                                                                      demo_root):
    """A script's background job (``cmd &``) starts with Ctrl-C ignored: the run goes on to the
    end, as it does with one worker, instead of stopping after half of its pairs with exit 0."""
    out = tmp_path / "ignored"
    proc = start("render", "--out", out, "--workers", "2", "-q", *FOUR, sigint=signal.SIG_IGN)
    assert wait_for(lambda: metadata_files(out) or proc.poll() is not None)
    os.killpg(proc.pid, signal.SIGINT)
    output = proc.communicate(timeout=300)[0].decode()
    assert proc.returncode == 0, output
    assert output == "", output
    assert sorted(recorded(out).values()) == ["written"] * 4
    assert len(metadata_files(out)) == 4


@pytest.mark.slow
def test_ctrl_c_to_the_group_of_a_run_with_workers_is_an_interruption_never_success(tmp_path,
                                                                                  demo_root):
    """Ctrl-C at the terminal: every process of the group gets SIGINT. The run stops with 130 and
    one line, the manifest lists exactly the pairs on disk, and --resume finishes the run."""
    out = tmp_path / "ctrl-c"
    proc = start("render", "--out", out, "--workers", "2", "-q", *FOUR)
    assert wait_for(lambda: metadata_files(out) or proc.poll() is not None)
    os.killpg(proc.pid, signal.SIGINT)
    output = proc.communicate(timeout=120)[0].decode()
    if proc.returncode == 0 and len(metadata_files(out)) == 4:
        pytest.skip("the run finished before the signal arrived")
    assert proc.returncode == 130, output
    written = [k for k, s in recorded(out).items() if s == "written"]
    assert output.splitlines() == [
        f"Interrupted after {len(written)} pair{'s' if len(written) != 1 else ''}; rerun with "
        "--resume to finish (finished pairs are kept)."], output
    assert len(written) == len(metadata_files(out)) >= 1
    assert not temp_files(out)
    res = run("render", "--out", out, "--workers", "2", "-q", "--resume", *FOUR)
    assert res.exit_code == 0, res.output
    assert sorted(recorded(out).values()) == ["written"] * 4


def test_stop_requests_leave_an_ignored_signal_ignored_and_never_end_as_success():
    from weathergen.workers import StopRequests

    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with StopRequests() as stop:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
        assert stop.signum is None and signal.getsignal(signal.SIGINT) == signal.SIG_IGN
        # a handler that returns (a library's logger, say): the cut-short work still raises
        seen = []
        signal.signal(signal.SIGTERM, lambda signum, frame: seen.append(signum))
        with pytest.raises(KeyboardInterrupt):
            with StopRequests():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
        assert seen == [signal.SIGTERM]
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


# -- 2 and 3: a worker killed (SIGKILL, as the out-of-memory killer sends) -----------------------

@pytest.mark.slow
def test_a_pair_that_kills_its_worker_fails_alone_and_every_finished_pair_is_recorded(tmp_path,
                                                                                      demo_root):
    """The worker loading courtyard 2 is killed each time: the pool breaks, the pairs in hand are
    rendered again one at a time, the culprit dies again and fails alone, naming the signal; the
    others are written and the manifest lists exactly what is on disk (no traceback, no temporary
    file)."""
    from fake_datasets import DemoKillingItsWorker
    from weathergen.engine import load_preset
    from weathergen.render import RenderJob, run_render

    dataset = DemoKillingItsWorker(frames_per_scene=2)
    deadly = [r for r in dataset.pairs() if r.id.scene == "courtyard" and r.id.frame == 2][0]
    dataset.deadly = {deadly.id.key}
    out = tmp_path / "killed"
    job = RenderJob(dataset=dataset, out=out, preset=load_preset("snow", {"count": "100"}),
                    preset_name="snow", workers=2)
    notes = []
    results = run_render(job, on_note=notes.append)
    status = {r.pair: r.status for r in results}
    assert status.pop(str(deadly.id)) == "failed"
    assert set(status.values()) == {"written"} and len(status) == 3
    failed = [r for r in results if r.status == "failed"][0]
    assert failed.message.startswith("its worker process died twice, the second time rendering "
                                     "it alone (killed by SIGKILL"), failed.message
    assert any(n.startswith("a worker process died (killed by SIGKILL") for n in notes), notes
    assert sorted(recorded(out).values()) == ["failed", "written", "written", "written"]
    assert len(metadata_files(out)) == 3
    assert not temp_files(out)


def digests(out: Path) -> dict:
    import hashlib

    return {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(out.rglob("*")) if p.is_file() and p.suffix in (".png", ".npz", ".flo")}


@linux_only
@pytest.mark.slow
def test_a_worker_killed_from_outside_is_one_note_and_its_pairs_are_rendered_again(tmp_path,
                                                                                   demo_root):
    """SIGKILL (the out-of-memory killer's signal) to a worker of a real run: no traceback, one
    note naming the signal, the lost pairs rendered again, exit 0, and the same files as a run
    where nothing happened; the manifest lists every pair."""
    out = tmp_path / "killed"
    proc = start("render", "--out", out, "--workers", "2", "-q", *FOUR)
    assert wait_for(lambda: len(workers_of(proc.pid)) == 2 or proc.poll() is not None)
    workers = workers_of(proc.pid)
    assert wait_for(lambda: metadata_files(out) or proc.poll() is not None)
    if proc.poll() is not None or not all(Path(f"/proc/{w}").exists() for w in workers):
        pytest.skip("the run finished before a worker could be killed")
    os.kill(workers[0], signal.SIGKILL)
    output = proc.communicate(timeout=300)[0].decode()
    if "worker process died" not in output and proc.returncode == 0:
        pytest.skip("the killed worker had nothing left to do")
    assert proc.returncode == 0, output
    assert "Traceback" not in output and "BrokenProcessPool" not in output, output
    lines = output.splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "Note: a worker process died (killed by SIGKILL"), output
    assert sorted(recorded(out).values()) == ["written"] * 4
    assert len(metadata_files(out)) == 4 and not temp_files(out)
    clean = tmp_path / "clean"
    assert run("render", "--out", clean, "-q", *FOUR).exit_code == 0
    assert digests(out) == digests(clean)


@linux_only
@pytest.mark.slow
def test_a_worker_killed_then_sigterm_stops_the_run_at_once_as_an_interruption(tmp_path,
                                                                                 demo_root):
    out = tmp_path / "term"
    proc = start("render", "--out", out, "--workers", "2", "-q", *FOUR)
    assert wait_for(lambda: metadata_files(out) or proc.poll() is not None)
    workers = workers_of(proc.pid)
    if proc.poll() is not None or not workers:
        pytest.skip("the run finished before a worker could be killed")
    os.kill(workers[0], signal.SIGKILL)
    time.sleep(0.3)
    proc.send_signal(signal.SIGTERM)
    output = proc.communicate(timeout=60)[0].decode()        # not minutes
    if proc.returncode == 0:
        pytest.skip("the run finished before the signal arrived")
    assert proc.returncode == 128 + signal.SIGTERM, output
    assert "Traceback" not in output and "BrokenProcessPool" not in output, output
    written = [k for k, s in recorded(out).items() if s == "written"]
    assert output.strip().splitlines()[-1] == (
        f"Interrupted after {len(written)} pair{'s' if len(written) != 1 else ''}; rerun with "
        "--resume to finish (finished pairs are kept).")
    assert len(written) == len(metadata_files(out)) >= 1
    assert not temp_files(out)
    assert not list(out.glob(".weathergen-lock*"))
    assert wait_for(lambda: not any(Path(f"/proc/{w}").exists() for w in workers), 10)


# -- 4: Ctrl-C while starting --------------------------------------------------------------------

@pytest.mark.slow
def test_ctrl_c_while_torch_is_imported_is_one_line_and_130(tmp_path):
    proc = start("render", "--out", tmp_path / "early", "-q")
    maps = Path(f"/proc/{proc.pid}/maps")
    if maps.parent.is_dir():                 # signal once torch's library is being loaded
        assert wait_for(lambda: proc.poll() is not None or b"libtorch" in _read(maps), 60, 0.002)
    else:
        time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    output = proc.communicate(timeout=120)[0].decode()
    assert proc.returncode == 130, output
    assert output == "Interrupted while starting; nothing was done.\n"
    assert not (tmp_path / "early").exists()


def _read(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError:
        return b""


def test_ctrl_c_in_a_command_that_does_not_handle_it_is_one_line_and_130(two_pairs, monkeypatch,
                                                                          tmp_path):
    import weathergen.cli.inspect_cmd as command

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(command, "contact_sheet", interrupted)
    res = run("preview", two_pairs, "--out", tmp_path / "sheet.png")
    assert res.exit_code == 130, res.output
    assert res.output == "Interrupted (SIGINT); no file was left half-written.\n"


def test_a_ctrl_c_that_surfaces_as_a_system_error_is_an_interruption(monkeypatch, tmp_path):
    """Ctrl-C inside some C calls surfaces as SystemError ("returned a result with an exception
    set", the KeyboardInterrupt its cause): still one line and 130, not a traceback."""
    import weathergen.cli.inspect_cmd as command

    def awkward(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise SystemError("<function PurePath.__str__> returned a result with an exception "
                              "set") from exc

    monkeypatch.setattr(command, "contact_sheet", awkward)
    res = run("preview", tmp_path, "--out", tmp_path / "sheet.png")
    assert res.exit_code == 130, res.output
    assert res.output == "Interrupted (SIGINT); no file was left half-written.\n"


# -- 5 and 6: videos: stopped writers, full disks ------------------------------------------------

@pytest.mark.slow
def test_a_stopped_video_writer_leaves_no_temporary_and_a_killed_ones_is_swept(two_pairs, tmp_path):
    """SIGTERM removes the temporary file; SIGKILL cannot, and the next write of the video
    removes it (both runs go at once)."""
    videos = {sig: tmp_path / sig.name / "v.mp4" for sig in (signal.SIGTERM, signal.SIGKILL)}
    procs = {}
    for sig, video in videos.items():
        video.parent.mkdir()
        procs[sig] = start("preview", two_pairs, "--video", video, "--cycles", "100", "--width",
                           "2048")            # 400 large frames: seconds to write
    for sig, proc in procs.items():
        folder = videos[sig].parent
        assert wait_for(lambda: list(folder.glob(".v.mp4.*")) or proc.poll() is not None)
        time.sleep(0.2)
        proc.send_signal(sig)
    term = procs[signal.SIGTERM].communicate(timeout=120)[0].decode()
    assert procs[signal.SIGTERM].returncode == 143, term
    assert term == "Interrupted (SIGTERM); no file was left half-written.\n"
    assert not list(videos[signal.SIGTERM].parent.iterdir())
    procs[signal.SIGKILL].wait(timeout=120)
    left = list(videos[signal.SIGKILL].parent.iterdir())
    assert len(left) == 1 and left[0].name.startswith(".v.mp4."), left
    res = run("preview", two_pairs, "--video", videos[signal.SIGKILL], "--cycles", "1")
    assert res.exit_code == 0, res.output
    assert [p.name for p in videos[signal.SIGKILL].parent.iterdir()] == ["v.mp4"]


def test_a_killed_previews_temporary_contact_sheet_is_swept_by_the_next(two_pairs, tmp_path):
    """A preview killed while writing its PNG leaves ``.sheet.png.PID.XXXXXXXX.tmp``; the next
    preview to that file removes it (that of a preview still running stays)."""
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                           capture_output=True, text=True).stdout.strip()
    left = tmp_path / f".sheet.png.{ended}.abcd1234.tmp"
    running = tmp_path / f".sheet.png.{os.getpid()}.efgh5678.tmp"
    for f in (left, running):
        f.write_bytes(b"half a png")
    res = run("preview", two_pairs, "--out", tmp_path / "sheet.png")
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == [running.name, "sheet.png"]


def _assert_full_disk_refused(res, video: Path) -> None:
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.output, res.output
    assert lines[0].startswith(f"Error: {video}: cannot write (No space left on device: the "
                               "video is incomplete"), lines[0]
    assert not video.exists() and not list(video.parent.glob(".v.mp4*"))


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 16 KiB file system, smaller than any preview video (root only; skipped where it cannot
    be mounted)."""
    folder = tmp_path / "small"
    folder.mkdir()
    if shutil.which("mount") is None or (hasattr(os, "geteuid") and os.geteuid() != 0):
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16k", "tmpfs", str(folder)],
                          capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    yield folder
    subprocess.run(["umount", str(folder)], check=False)


def test_a_video_on_a_full_file_system_is_one_line_and_no_file(two_pairs, small_tmpfs):
    video = small_tmpfs / "v.mp4"
    _assert_full_disk_refused(run("preview", two_pairs, "--video", video), video)


def test_a_video_writer_that_stops_mid_file_is_caught(two_pairs, tmp_path, monkeypatch):
    """Where no small file system can be mounted: OpenCV's writer cut off after 20 000 bytes, as
    on a full disk (it says nothing), and the disk reported full."""
    import cv2

    import weathergen.io.video as video_io

    class CutOff:
        def __init__(self, path, *args):
            self.path, self.inner = path, cv2.VideoWriter(path, *args)

        def isOpened(self):
            return self.inner.isOpened()

        def write(self, frame):
            self.inner.write(frame)

        def release(self):
            self.inner.release()
            data = Path(self.path).read_bytes()
            Path(self.path).write_bytes(data[:20_000])

    class Cv2:
        def __getattr__(self, name):
            return CutOff if name == "VideoWriter" else getattr(cv2, name)

    monkeypatch.setattr(video_io, "cv2", Cv2())
    monkeypatch.setattr(video_io, "_disk_full", lambda folder: True)
    video = tmp_path / "cut" / "v.mp4"
    video.parent.mkdir()
    _assert_full_disk_refused(run("preview", two_pairs, "--video", video, "--cycles", "3"), video)


# -- 7 and 8: unit slips and memory --------------------------------------------------------------

def test_a_diameter_in_millimetres_is_refused_naming_the_slip(tmp_path):
    res = run("render", "--preset", "snow-moderate", "--set", "diameter=8", "--out",
              tmp_path / "o", "-q")
    assert res.exit_code == 2, res.output
    assert res.output == ("Error: --set: key 'diameter' = 8.0: 8 m is outside the plausible "
                          "0.0001 to 0.1 m for particles (flakes templates); did you mean 0.008 m "
                          "(8 mm)?\n")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("key, value, expected", [
    ("visibility", "0.3", "must be 0 (clear air) or a visibility in metres in [10, 200000] (fog: "
                          "below 1000, mist and haze: 1000 to 10000); did you mean 300 m (0.3 km)?"),
    ("sky_distance", "2", "2 m is outside the plausible 10 to 1e+06 m; did you mean 2000 m (2 km)?"),
    ("snow_rate", "50", "must lie in [0, 30]")])
def test_an_atmospheres_distance_in_kilometres_is_refused_naming_the_slip(key, value, expected):
    res = run("render", "--preset", "fog-light", "--set", f"{key}={value}", "-q")
    assert res.exit_code == 2, res.output
    assert res.output.startswith(f"Error: --set: key '{key}' = "), res.output
    assert res.output.rstrip().endswith(expected) and len(res.output.splitlines()) == 1, res.output


def test_a_pair_that_would_not_fit_the_memory_budget_is_refused_before_drawing(tmp_path):
    res = run("render", "--preset", "snow-heavy", "--scenes", "street", "--frames-per-scene", "1",
              "--out", tmp_path / "o", "-q", env={"WEATHERGEN_MEMORY_BUDGET": "64M"})
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    line = res.output.strip().splitlines()[-1]
    assert line.startswith("Error: every selected pair failed (1; the first: "
                           "demo/training/street/0001: drawing this pair needs about "), line
    assert "more than the 64.0 MiB available (WEATHERGEN_MEMORY_BUDGET)" in line
    assert "lower the preset keys density (now 350) or far (now 10)" in line
    assert not (tmp_path / "o").exists()
    res = run("render", "--preset", "snow-heavy", "--scenes", "street", "--frames-per-scene", "1",
              "--out", tmp_path / "o", "-q", env={"WEATHERGEN_MEMORY_BUDGET": "a lot"})
    assert res.exit_code == 2
    assert res.output == ("Error: WEATHERGEN_MEMORY_BUDGET: 'a lot' is not an amount of memory "
                          "(e.g. 512M, 4G)\n")


def test_an_allocation_that_fails_anyway_fails_its_pair_in_one_line(tmp_path, monkeypatch):
    """Where the estimate falls short (or something else took the memory meanwhile) the
    allocator's error fails that pair with one line saying what to lower; the other pairs are
    written, exit 1. Any other error is not taken for one."""
    import weathergen.render.job as render_job

    real = render_job.render_pair

    def allocating(pair, particles, **kwargs):
        if "street" in str(getattr(pair, "id", "")):
            raise RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator:"
                               " can't allocate memory: you tried to allocate 1073741824 bytes. "
                               "Error code 12 (Cannot allocate memory)")
        return real(pair, particles, **kwargs)

    monkeypatch.setattr(render_job, "render_pair", allocating)
    out = tmp_path / "o"
    res = run("render", "--frames-per-scene", "1", "--set", "count=50", "--out", out, "-q")
    assert res.exit_code == 1, res.output
    assert res.output.splitlines() == [
        "failed demo/training/street/0001: ran out of memory (tried to allocate "
        "1.0 GiB); lower the preset's particle count or density (or its far depth), or draw "
        "fewer pairs at once (--workers, --batch-size)",
        "1 pair failed; see the messages above and the manifest."], res.output
    assert sorted(recorded(out).values()) == ["failed", "written"]
    assert len(metadata_files(out)) == 1 and not temp_files(out)
    from weathergen.memory import out_of_memory

    assert out_of_memory(MemoryError()) == "an allocation failed"
    assert out_of_memory(RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB")) == \
        "tried to allocate 2.00 GiB"
    assert out_of_memory(RuntimeError("shape mismatch")) is None
    assert out_of_memory(ValueError("out of memory")) is None


def test_an_attack_whose_allocation_fails_fails_its_pairs_in_one_line(tmp_path, monkeypatch,
                                                                     raft_small_weights):
    import weathergen.attack.job as attack_job

    def allocating(*args, **kwargs):
        raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate "
                           "3221225472 bytes. Error code 12 (Cannot allocate memory)")

    monkeypatch.setattr(attack_job, "attack_batch", allocating)
    res = run("attack", "--model", "raft-small", "--checkpoint", raft_small_weights, "--iters",
              "1", "--steps", "1", "--scenes", "street", "--frames-per-scene", "1", "--set",
              "count=50", "--out", tmp_path / "a", "-q")
    assert res.exit_code == 1, res.output           # as attack --help says: failures recorded
    assert res.output.splitlines() == [
        "failed demo/training/street/0001: ran out of memory (tried to allocate 3.0 GiB); lower "
        "the preset's particle count or density (or its far depth), or draw fewer pairs at once "
        "(--batch-size)", "1 pair failed; see the messages above."], res.output
    assert list(recorded(tmp_path / "a").values()) == ["failed"]


@pytest.mark.parametrize("epsilon, slip", [("1e9", ""), ("8", "; did you mean 0.03137 (8 on the "
                                                               "0-255 scale)?")])
def test_an_lp_epsilon_beyond_pixel_values_is_refused(tmp_path, epsilon, slip):
    res = run("attack", "--method", "pcfa", "--epsilon", epsilon, "--out", tmp_path / "a", "-q")
    assert res.exit_code == 2, res.output
    value = f"{float(epsilon):g}"
    assert res.output == (f"Error: --epsilon {value}: {value} is outside the plausible 0 to 1 for "
                          f"perturbations of pixel values in [0, 1]{slip}\n")


# -- 9: ground-truth flow that is all NaN, or missing -------------------------------------------

def test_non_finite_or_missing_ground_truth_flow_is_a_warning(fake_sintel, tmp_path):
    from weathergen.io.sintel_formats import read_flo, write_flo

    flows = sorted((fake_sintel / "training" / "flow" / "alley").glob("*.flo"))
    write_flo(flows[0], np.full_like(read_flo(flows[0]), np.nan))
    flows[1].unlink()
    out = tmp_path / "o"
    res = run("render", "--root", fake_sintel, "--scenes", "alley", "--set", "count=20", "--out",
              out, "-q")
    assert res.exit_code == 0, res.output
    assert res.output.splitlines() == [
        f"warning sintel/training/alley/0001: {flows[0]}: the ground-truth flow has no valid "
        "vector (192 of 192 not finite); it is written as invalid everywhere",
        f"warning sintel/training/alley/0002: {flows[1]}: ground-truth flow file is missing (the "
        "scene's other pairs have one); the pair is written without flow"]
    written = read_flo(out / "training" / "flow" / "alley_0001" / "frame_0001.flo")
    assert np.isfinite(written).all()
    assert (out / "training" / "invalid" / "alley_0001" / "frame_0001.png").exists()
    assert not (out / "training" / "flow" / "alley_0002").exists()
    pairs = json.loads((out / "manifest.json").read_text())["pairs"]
    assert sorted(len(p["warnings"]) for p in pairs.values()) == [0, 1, 1]


# -- 10: preview of an output with a corrupt particle file --------------------------------------

@pytest.mark.slow
def test_preview_says_which_pair_it_leaves_out_for_a_corrupt_particle_file(two_pairs, tmp_path):
    out = tmp_path / "corrupt"
    shutil.copytree(two_pairs, out)
    meta = out / "training" / "particles" / "street_0001" / "frame_0001.npz"
    meta.write_bytes(meta.read_bytes()[:300])
    line = (f"warning: {meta}: not a readable .npz metadata file (File is not a zip file); "
            "{} is left out")
    res = run("preview", out)
    assert res.exit_code == 1, res.output
    assert res.output.splitlines() == [f"Preview of 1 pair written to {out / 'preview.png'}",
                                       line.format("pair demo/training/street/0001")]
    res = run("preview", out, "--video", tmp_path / "v.gif", "--cycles", "1")
    assert res.exit_code == 1, res.output
    assert res.output.splitlines()[1:] == [line.format("its pair")]
    assert (tmp_path / "v.gif").exists()


# -- 11: a layer's model changed by an override -------------------------------------------------

def test_an_override_cannot_turn_a_field_layer_into_the_paper_model(tmp_path):
    res = run("render", "--preset", "snow-moderate+fog-light", "--set", "fog-light.model=paper",
              "--out", tmp_path / "o", "-q")
    assert res.exit_code == 2, res.output
    assert res.output.startswith("Error: --preset snow-moderate+fog-light: layer 2 (fog-light): "
                                 "preset fog-light (fog-light.toml): key 'model' = 'paper': "
                                 "fog-light is a field preset, and an override cannot change its "
                                 "model"), res.output
    assert len(res.output.splitlines()) == 1 and "Traceback" not in res.output
    assert not (tmp_path / "o").exists()
    res = run("presets", "fog-light", "--set", "model=field")     # its own model: fine
    assert res.exit_code == 0, res.output


def test_a_model_override_without_a_layer_is_checked_by_each_layer(tmp_path):
    """Every preset may name its model, so a bare --set model=... of a combined preset reaches
    each layer, and the first whose model it is not says so (not "no layer has this key")."""
    res = run("render", "--preset", "snow-moderate+fog-light", "--set", "model=paper", "--out",
              tmp_path / "o", "-q")
    assert res.exit_code == 2, res.output
    assert res.output.startswith("Error: --preset snow-moderate+fog-light: layer 1 "
                                 "(snow-moderate): preset snow-moderate (snow-moderate.toml): key "
                                 "'model' = 'paper': snow-moderate is a field preset, and an "
                                 "override cannot change its model"), res.output
    assert len(res.output.splitlines()) == 1
    res = run("presets", "snow+fog-light", "--set", "model=field")
    assert res.exit_code == 2
    assert "layer 1 (snow): preset snow (snow.toml): key 'model' = 'field': snow is a paper " \
           "preset" in res.output
    res = run("presets", "fog-light", "--set", "model=fields")
    assert res.exit_code == 2
    assert res.output == ("Error: preset fog-light (fog-light.toml): key 'model' = 'fields':"
                          " must be paper or field\n")
    res = run("presets", "snow-moderate+fog-light", "--set", "model=field")    # theirs: fine
    assert res.exit_code == 0, res.output


# -- every command's --help states its exit codes -----------------------------------------------

def _commands(group=cli, path=()):
    """Every command line of the group, its subgroups' commands too: ``("render",)``, ..."""
    import click

    yield path
    for name, command in sorted(group.commands.items()):
        if isinstance(command, click.Group):
            yield from _commands(command, (*path, name))
        else:
            yield (*path, name)


def test_the_walk_finds_every_command():
    assert {"render", "attack", "preview", "presets", "inspect"} <= {c[-1] for c in _commands()
                                                                    if c}


@pytest.mark.parametrize("command", list(_commands()), ids=lambda c: " ".join(c) or "weathergen")
def test_help_states_the_exit_codes(command):
    """0, 2 and 130/143 (every command turns Ctrl-C and SIGTERM into one line) at least, each
    with what it means, in the order of the codes."""
    res = run(*command, "--help")
    assert res.exit_code == 0, res.output
    assert "Exit codes:\n" in res.output, res.output
    lines = [line for line in res.output.split("Exit codes:\n", 1)[1].splitlines() if line.strip()]
    indent = min(len(line) - len(line.lstrip()) for line in lines)
    entries = [re.fullmatch(r"(\d+(?:, \d+)*) {2,}(\S.*)", line[indent:])
               for line in lines if line[indent:indent + 1].strip()]
    assert all(entries), lines                            # each code with what it means
    listed = [c for entry in entries for c in entry.group(1).split(", ")]
    assert listed == sorted(listed, key=int) and listed[0] == "0", lines
    assert {"2", "130", "143"} <= set(listed), lines
