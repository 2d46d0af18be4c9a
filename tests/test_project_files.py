"""Promises of the Makefile and README that are about the project, not the library."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from conftest import PROJECT_ROOT

README = (PROJECT_ROOT / "README.md").read_text()


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_make_with_another_torch_takes_effect_once_the_venv_exists(tmp_path):
    """`make test TORCH=...` reinstalls torch in an existing venv; an unchanged TORCH installs nothing."""
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    log = tmp_path / "pip.log"
    stub = venv / "bin" / "python"          # records what make asks pip to do
    stub.write_text(f'#!/bin/sh\necho "$@" >> "{log}"\n')
    stub.chmod(0o755)

    def make(torch):
        log.write_text("")
        subprocess.run(["make", "-s", "-C", str(PROJECT_ROOT), "venv", f"VENV={venv}", f"TORCH={torch}"],
                       check=True, capture_output=True)
        return log.read_text().splitlines()

    assert make("torch==2.13.0") == ["-m pip install -q torch==2.13.0", "-m pip install -q .[test]"]
    assert make("torch==2.13.0") == []
    assert make("torch==2.5.1") == ["-m pip install -q --force-reinstall --no-deps torch==2.5.1",
                                    "-m pip install -q torch==2.5.1", "-m pip install -q .[test]"]
    assert make("torch==2.5.1") == []


def _demo_out() -> str:
    makefile = (PROJECT_ROOT / "Makefile").read_text()
    recipe = makefile.split("\ndemo:", 1)[1].split("\n\n", 1)[0]
    return re.search(r"render .*--out (\S+)", recipe).group(1)


def test_the_readme_first_command_works_after_make_demo():
    """After `make demo` the README's first `weathergen render` finds the command and a free folder."""
    first = re.search(r"^weathergen render\b.*$", README, re.M).group(0)
    assert "--out" not in first.split("#")[0]          # writes into the default out/snow
    assert _demo_out() != "out/snow"
    # the README says how to reach the installed command before its first use
    setup = README.split("## A five-minute tour", 1)[0]
    assert ". .venv/bin/activate" in setup and ".venv/bin/weathergen" in setup


def test_the_readme_names_what_make_demo_writes():
    """The README's `make demo` line names the folder the recipe renders into and the contact
    sheet its `weathergen preview` writes there (preview's default, RENDER_DIR/preview.png)."""
    said = re.search(r"^make demo\s+#(.*)$", README, re.M).group(1)
    out = _demo_out()
    recipe = (PROJECT_ROOT / "Makefile").read_text().split("\ndemo:", 1)[1].split("\n\n", 1)[0]
    assert re.search(rf"weathergen preview {re.escape(out)}\s*$", recipe, re.M), recipe
    assert f"{out}," in said and f"{out}/preview.png" in said, said


def test_every_test_the_guarantees_name_exists():
    """docs/guarantees.md (the README links to it) names the test behind each guarantee."""
    assert "(docs/guarantees.md)" in README
    named = set(re.findall(r"`(test_\w+)`", (PROJECT_ROOT / "docs" / "guarantees.md").read_text()))
    assert len(named) >= 40
    defined = set()
    for path in (PROJECT_ROOT / "tests").rglob("test_*.py"):
        defined |= set(re.findall(r"^def (test_\w+)\(", path.read_text(), re.M))
    assert named <= defined, f"docs/guarantees.md names tests that do not exist: {sorted(named - defined)}"


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
@pytest.mark.parametrize("target", ["demo", "test", "test-slow"])
def test_make_says_what_it_installs_before_each_long_silent_step(tmp_path, target):
    """`make demo`, `make test` and `make test-slow` on a fresh machine print a line before each quiet pip install
    (torch takes minutes) and before the tests, so they are never silent for minutes unexplained."""
    venv = tmp_path / "venv"
    plan = subprocess.run(["make", "-n", "-C", str(PROJECT_ROOT), target, f"VENV={venv}"],
                          check=True, capture_output=True, text=True).stdout.splitlines()
    installs = [i for i, line in enumerate(plan) if "pip install -q" in line and "--no-deps" not in line]
    assert len(installs) == 2                      # torch, then the package's dependencies
    for i in installs:
        assert "echo" in plan[i - 1] and "installing" in plan[i - 1], plan[i - 1]
    assert "torch" in plan[installs[0] - 1] and "minutes" in plan[installs[0] - 1]
    if target.startswith("test"):
        pytest_line = next(i for i, line in enumerate(plan) if "bin/pytest -q" in line)
        assert "echo" in plan[pytest_line - 1] and "minutes" in plan[pytest_line - 1]


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_ci_runs_the_quick_tests_and_then_the_slow_ones(tmp_path):
    """`make test` selects the tests not marked slow, `make test-slow` those marked slow, and CI
    runs both: together they are every test, each once."""
    def pytest_line(target):
        plan = subprocess.run(["make", "-n", "-C", str(PROJECT_ROOT), target, f"VENV={tmp_path / 'v'}"],
                              check=True, capture_output=True, text=True).stdout.splitlines()
        return next(line for line in plan if "bin/pytest -q" in line)
    assert '-m "not slow"' in pytest_line("test")
    assert "-m slow" in pytest_line("test-slow")
    steps = [line.strip() for line in (PROJECT_ROOT / ".ci" / "run").read_text().splitlines()
             if line.strip().startswith("make ")]
    assert steps == ["make test", "make test-slow"]
