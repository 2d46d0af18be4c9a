"""`make gpu-check` (speed/gpu_check.py): one table of every CUDA test and GPU benchmark.

No GPU is needed here: without CUDA the command says so in one line; the table is assembled on
the CPU by the dry run (``--device cpu --quick``), whose figures mean nothing.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import pytest
import torch

from conftest import PROJECT_ROOT
from run_helpers import script_module

SCRIPT = PROJECT_ROOT / "speed" / "gpu_check.py"


@pytest.fixture(scope="module")
def gpu_check():
    with script_module(SCRIPT) as module:
        yield module


def run_script(*args, cwd=PROJECT_ROOT):
    return subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=900)


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is here: the check would run")
def test_without_cuda_it_stops_at_once_with_one_line():
    for args in ((), ("--probe",)):
        res = run_script(*args)
        assert res.returncode == 2 and res.stdout == "", res
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("gpu-check needs a CUDA device"), res.stderr
        assert "make gpu-check TORCH=torch" in lines[0]
    res = run_script("--device", "cpu")
    assert res.returncode == 2 and "needs --quick" in res.stderr


def test_every_test_that_needs_cuda_carries_the_marker_gpu_check_selects():
    """A test skipped by its own CUDA condition would be left out of `pytest -m cuda`."""
    own_skips = [f"{path.relative_to(PROJECT_ROOT)}:{n}"
                 for path in sorted((PROJECT_ROOT / "tests").rglob("*.py"))
                 for n, line in enumerate(path.read_text().splitlines(), 1)
                 if re.search(r"skipif\(\s*not\s+torch\.cuda\.is_available\(\)", line)]
    assert own_skips == [], "use @pytest.mark.cuda instead of skipif on CUDA"


def test_the_makefile_target_probes_before_it_installs_anything():
    makefile = (PROJECT_ROOT / "Makefile").read_text()
    recipe = makefile.split("\ngpu-check:", 1)[1].split("\n\n", 1)[0]
    commands = [line.strip() for line in recipe.splitlines()[1:]]
    assert "gpu_check.py --probe" in commands[0], commands
    # the figures file and its page (docs/figures/gpu-check.json, gpu.md) unless GPU_FIGURES says
    assert any(c.endswith("gpu_check.py --json $(GPU_FIGURES)/gpu-check.json") for c in commands[1:]), \
        commands
    assert "\nGPU_FIGURES ?= docs/figures\n" in makefile


def test_table_and_summary_parsing(gpu_check):
    counts = gpu_check.pytest_counts("....\nFAILED tests/x.py::t - boom\n3 failed, 12 passed, "
                                     "2 skipped, 1 error in 4.2s\n")
    assert counts == {"failed": 3, "passed": 12, "skipped": 2, "error": 1}
    assert gpu_check.pytest_counts("no summary") == {}
    Row = gpu_check.Row
    text = gpu_check.table([Row("render", "snow, forward", 0.01234, 1.5),
                            Row("tests", "pytest -m cuda", 9.0, None, "3 passed", failed=True)],
                           "title")
    assert text.splitlines() == [
        "title", "", "| area | what | seconds | GPU memory (GiB) | note |", "|---|---|---:|---:|---|",
        "| render | snow, forward | 0.012 | 1.50 |  |",
        "| tests | pytest -m cuda | 9.000 | – | FAILED: 3 passed |"]


def test_the_networks_measured_by_default_are_every_registered_one(gpu_check, monkeypatch):
    from weathergen.models import available_models, registry

    assert sorted(gpu_check.every_network()) == sorted(available_models())
    assert gpu_check.every_network()[:2] == ["raft-small", "raft"]          # the tables' order
    # a network registered later is measured too, after the others
    monkeypatch.setattr(registry, "_ARCHITECTURES", {**registry._ARCHITECTURES, "a-new-net": None})
    assert gpu_check.every_network()[-1] == "a-new-net"


def test_an_area_that_fails_is_one_failed_row_and_the_others_still_run(gpu_check, monkeypatch):
    def broken(device, sizes):
        raise RuntimeError("CUDA out of memory")

    monkeypatch.setattr(gpu_check, "AREAS", {"render": broken,
                                             "field": lambda d, s: [gpu_check.Row("field", "x", 1.0)]})
    monkeypatch.setattr(gpu_check, "network_rows", lambda d, s, m: [])
    rows = gpu_check.run("cpu", gpu_check.QUICK, [], tests=False)
    assert [(r.area, r.failed) for r in rows] == [("render", True), ("field", False)]
    assert rows[0].note == "RuntimeError: CUDA out of memory"


@pytest.mark.slow
def test_the_dry_run_measures_every_area_into_one_table(tmp_path):
    out = tmp_path / "figures.json"
    res = run_script("--device", "cpu", "--quick", "--models", "spynet", "--json", out)
    assert res.returncode == 0, res.stdout + res.stderr
    figures = json.loads(out.read_text())
    rows = figures["rows"]
    assert figures["machine"]["gpu"] is None and len(figures["tree"]["commit"]) == 40
    page = (tmp_path / "gpu.md").read_text()          # rewritten beside the JSON
    assert "## make gpu-check" in page and "(dry run: tiny inputs)" in page
    assert "### networks" in page and "| spynet |" in page
    assert {r["area"] for r in rows} == {"render", "field", "training", "attack batch", "tables",
                                         "networks"}
    assert not [r for r in rows if r["failed"]]
    assert all(r["seconds"] > 0 for r in rows if not r["what"].startswith("Tables 2-5"))
    whats = {r["what"] for r in rows}
    assert {"snow (100), forward", "fog (4), forward + backward", "spynet, forward + backward",
            "raft-small, batch of 2: a step", "snow-heavy: render a frame"} <= whats
    assert any(w.startswith("raft-small: attack step at batch ") for w in whats)
    assert any(w.startswith("Tables 2-5 on Sintel, 1 network(s): ") for w in whats)
    table = [line for line in res.stdout.splitlines() if line.startswith("| ")]
    assert table[0] == "| area | what | seconds | GPU memory (GiB) | note |"
    assert len(table) == 1 + len(rows)            # the header and one line per figure
