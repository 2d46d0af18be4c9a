"""The command line: help, version, check and demo-scene, with their error paths."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from click.testing import CliRunner

import weathergen
from weathergen.cli.main import _register, cli


def run(*args):
    _register()
    return CliRunner().invoke(cli, list(args))


def test_help_lists_commands():
    res = run("--help")
    assert res.exit_code == 0
    for cmd in ("check", "demo-scene"):
        assert cmd in res.output


def test_version():
    res = run("--version")
    assert res.exit_code == 0 and weathergen.__version__ in res.output


def test_check_demo_scene_passes(demo_root):
    res = run("check")
    assert res.exit_code == 0, res.output
    assert "courtyard" in res.output and "All 6 pairs" in res.output


def test_check_fake_sintel_with_a_corrupt_file(fake_sintel):
    assert run("check", "--root", str(fake_sintel)).exit_code == 0
    (fake_sintel / "training/depth/bamboo/frame_0003.dpt").write_bytes(b"junk")
    res = run("check", "--root", str(fake_sintel), "--scenes", "bamboo")
    assert res.exit_code == 1
    assert "frame_0003.dpt" in res.output and "cannot be read" in res.output


def test_check_test_split_reports_missing_depth(fake_sintel):
    res = run("check", "--root", str(fake_sintel), "--split", "test", "--frames-per-scene", "1")
    assert res.exit_code == 1
    assert "alley: depth file is missing (the Sintel test split ships no depth or camera files, which " \
           "weather needs): test/depth/alley/frame_0001.dpt, test/depth/alley/frame_0002.dpt\n" in res.output


def test_check_error_paths(tmp_path, fake_sintel):
    res = run("check", "--root", str(tmp_path / "absent"))
    assert res.exit_code == 2
    assert "absent: dataset root does not exist" in res.output
    assert "Traceback" not in res.output
    res = run("check", "--root", str(fake_sintel), "--scenes", "nope")
    assert res.exit_code == 2 and "available: alley, bamboo" in res.output
    res = run("check", "--root", str(fake_sintel), "--pass", "albedo")
    assert res.exit_code == 2 and "no pass named 'albedo'; available: clean, final" in res.output
    res = run("check", "--dataset", "kitti9")
    assert res.exit_code == 2 and "Invalid value" in res.output


def test_demo_scene_command(tmp_path):
    out = tmp_path / "scene"
    res = run("demo-scene", str(out))
    assert res.exit_code == 0, res.output
    assert (out / "training/clean/street/frame_0001.png").exists()
    from weathergen.io.atomic import UMASK

    assert out.stat().st_mode & 0o777 == 0o777 & ~UMASK, "a plain folder, not a private temporary one"
    assert run("check", "--root", str(out)).exit_code == 0
    res = run("demo-scene", str(out))
    assert res.exit_code == 2 and "not empty" in res.output
    assert run("demo-scene", str(out), "--overwrite").exit_code == 0


def test_installed_console_script(fake_sintel):
    """The console script of the installed distribution (not only the module) works."""
    script = Path(sys.executable).parent / "weathergen"
    assert script.exists(), f"no console script at {script}"
    out = subprocess.run([str(script), "check", "--root", str(fake_sintel)], capture_output=True,
                         text=True, env=os.environ)
    assert out.returncode == 0, out.stderr
    assert "alley" in out.stdout


def test_options_gathered_into_a_settings_record():
    """A command's options named as a record's fields come in as one record; the others as
    they are; its --help is that of its options."""
    import click

    from weathergen.cli.options import RunOptions, gathered

    seen = {}

    @click.command()
    @click.option("--device", default="cpu")
    @click.option("--executor", default="local")
    @click.option("--ray-address", default="auto")
    @click.option("--batch-size", type=int, default=None)
    @click.option("--resume", is_flag=True)
    @click.option("--overwrite", is_flag=True)
    @click.option("--seed", type=int, default=0)
    @gathered("run", RunOptions)
    def command(seed, run):
        seen.update(seed=seed, run=run)

    res = CliRunner().invoke(command, ["--batch-size", "3", "--resume", "--seed", "7"])
    assert res.exit_code == 0, res.output
    assert seen == {"seed": 7, "run": RunOptions(batch_size=3, resume=True)}
    assert "--ray-address" in CliRunner().invoke(command, ["--help"]).output
