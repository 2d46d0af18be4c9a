"""Render and attack as Ray tasks on a local Ray cluster started here: the same bytes as local
runs, a killed worker's pair retried and complete, and a killed driver's run resumed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

ray = pytest.importorskip("ray")

pytestmark = pytest.mark.slow

PAIRS = ["--scenes", "courtyard,street", "--frames-per-scene", "1"]
RENDER = ["render", "--preset", "snow", "--set", "count=300", "--seed", "4", *PAIRS]


def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def files(folder: Path) -> dict[str, bytes]:
    """Every file of an output but its run records (manifest, run config, logs with timings)."""
    skip = {"manifest.json", ".config.json", "summary.json"}
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name not in skip and "manifest.d" not in p.parts
            and "attack_log" not in p.parts}


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """One local Ray for the module (starting Ray is slow); its address for other drivers.

    Ray puts the driver's working directory on its workers' import path: start from a folder
    without a source tree, so that workers import the installed package as users' do.
    """
    before = os.getcwd()
    os.chdir(tmp_path_factory.mktemp("ray"))
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        yield ray.get_runtime_context().gcs_address
        ray.shutdown()
    finally:
        os.chdir(before)


@pytest.fixture(scope="module")
def local_render(tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "snow"
    assert invoke([*RENDER, "--out", out]).exit_code == 0
    return out


def test_render_on_ray_writes_the_local_bytes(cluster, local_render, tmp_path):
    out = tmp_path / "snow"
    result = invoke([*RENDER, "--out", out, "--executor", "ray", "--ray-address", cluster,
                     "--batch-size", "1"])
    assert result.exit_code == 0, result.output
    assert files(out) == files(local_render) and files(out)
    manifest = json.loads((out / "manifest.json").read_text())
    entries = list(manifest["pairs"].values())
    assert len(entries) == 2 and all(e["status"] == "written" for e in entries)
    # Accounting: each pair ran in a Ray worker process, not in this driver.
    assert all(e["ran"]["worker"] and e["ran"]["pid"] != os.getpid() for e in entries)
    assert all(e["seconds"] > 0 for e in entries)


def test_attack_on_ray_writes_the_local_bytes(cluster, raft_small_weights, tmp_path):
    args = ["attack", "--model", "raft-small", "--checkpoint", raft_small_weights, "--iters", "1",
            *PAIRS, "--steps", "1", "--set", "count=60", "--seed", "2", "--batch-size", "2"]
    local = invoke([*args, "--out", tmp_path / "local"])
    assert local.exit_code == 0, local.output
    remote = invoke([*args, "--out", tmp_path / "ray", "--executor", "ray",
                     "--ray-address", cluster])
    assert remote.exit_code == 0, remote.output
    assert files(tmp_path / "ray") == files(tmp_path / "local") and files(tmp_path / "local")
    manifest = json.loads((tmp_path / "ray" / "manifest.json").read_text())
    entries = list(manifest["pairs"].values())
    assert [e["ran"]["batch"] for e in entries] == [2, 2]     # both pairs in one batch
    assert manifest["runs"][-1]["executor"] == "ray"


def test_lp_attack_batched_on_ray_writes_the_local_bytes(cluster, raft_small_weights, tmp_path):
    """An Lp baseline goes through the same work units: batched, and as Ray tasks."""
    args = ["attack", "--method", "ifgsm", "--model", "raft-small", "--checkpoint",
            raft_small_weights, "--iters", "1", *PAIRS, "--steps", "1", "--seed", "2",
            "--batch-size", "2", "--quiet"]
    local = invoke([*args, "--out", tmp_path / "local"])
    assert local.exit_code == 0, local.output
    remote = invoke([*args, "--out", tmp_path / "ray", "--executor", "ray",
                     "--ray-address", cluster])
    assert remote.exit_code == 0, remote.output
    written = files(tmp_path / "local")
    assert any(name.endswith(".exr") for name in written)      # the float frames, too
    assert files(tmp_path / "ray") == written
    for run in ("local", "ray"):
        manifest = json.loads((tmp_path / run / "manifest.json").read_text())
        assert [e["ran"]["batch"] for e in manifest["pairs"].values()] == [2, 2]
        assert manifest["config"]["attack"]["method"] == "ifgsm"
    assert manifest["runs"][-1]["executor"] == "ray"


class KillOnce:
    """A dataset whose worker process dies (SIGKILL) the first time it loads ``victim``."""

    def __init__(self, inner, flag: Path, victim: str, sleep: float = 0.0):
        self.inner, self.flag, self.victim, self.sleep = inner, flag, victim, sleep

    def __getattr__(self, name):
        if name.startswith("_") or name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def pairs(self):
        return self.inner.pairs()

    def describe(self):
        return self.inner.describe()

    def load(self, ref):
        if ref.id.scene == self.victim and not self.flag.exists():
            self.flag.write_text(str(os.getpid()))
            if self.sleep:
                time.sleep(self.sleep)
            else:
                os.kill(os.getpid(), signal.SIGKILL)
        return self.inner.load(ref)


def render_job(dataset, out: Path, address: str):
    from weathergen.engine import load_preset, parse_set_options
    from weathergen.render import RenderJob

    return RenderJob(dataset=dataset, out=out,
                     preset=load_preset("snow", parse_set_options(["count=300"])),
                     preset_name="snow", seed=4, pass_name="snow_clean", executor="ray",
                     ray_address=address)


def demo_dataset():
    from weathergen.datasets import open_dataset

    return open_dataset("demo", None, scenes=["courtyard", "street"], frames_per_scene=1)


def test_a_killed_worker_is_retried_and_leaves_no_partial_file(cluster, local_render, tmp_path):
    from weathergen.render import run_render

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    flag = tmp_path / "killed"
    out = tmp_path / "snow"
    results = run_render(render_job(KillOnce(demo_dataset(), flag, "street"), out, cluster))
    assert flag.exists() and int(flag.read_text()) != os.getpid()     # a worker was killed
    assert sorted(r.status for r in results) == ["written", "written"]
    assert files(out) == files(local_render)
    assert not [p for p in out.rglob("*.tmp")]


def test_a_run_resumes_after_its_driver_is_killed(cluster, local_render, tmp_path):
    """The driver dies while one pair is in progress; --resume finishes the run."""
    flag = tmp_path / "started"
    out = tmp_path / "snow"
    script = tmp_path / "driver.py"
    script.write_text(textwrap.dedent(f"""
        import sys
        from pathlib import Path
        import ray
        sys.path.insert(0, {str(Path(__file__).parent)!r})
        import test_ray_executor as t
        ray.cloudpickle.register_pickle_by_value(t)
        ray.init(address={cluster!r}, log_to_driver=False)
        from weathergen.render import run_render
        run_render(t.render_job(t.KillOnce(t.demo_dataset(), Path({str(flag)!r}), "street",
                                           sleep=600), Path({str(out)!r}), {cluster!r}))
    """))
    driver = subprocess.Popen([sys.executable, "-P", str(script)], env=os.environ.copy(),
                              cwd=tmp_path)
    try:
        # the other pair is complete once its particle file (written last) is there
        other = out / "training" / "particles" / "courtyard_0001" / "frame_0001.npz"
        deadline = time.monotonic() + 240
        while not (flag.exists() and other.exists()):
            assert driver.poll() is None, "the driver ended before it could be killed"
            assert time.monotonic() < deadline, "the driver made no progress"
            time.sleep(0.2)
    finally:
        driver.kill()                                  # SIGKILL, whatever happened
        driver.wait()
    assert not (out / "training" / "particles" / "street_0001").exists()
    resumed = invoke([*RENDER, "--out", out, "--executor", "ray", "--ray-address", cluster,
                      "--resume"])
    assert resumed.exit_code == 0, resumed.output
    assert files(out) == files(local_render)
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(e["status"] for e in manifest["pairs"].values()) == ["skipped", "written"]
