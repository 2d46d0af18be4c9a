"""speed/gpu_session.py, the short GPU session of speed measurements, run on the CPU on tiny
sizes (its figures mean nothing there): the sections the table benchmark's tests do not cover
run to the end and write their figures, and without CUDA the script stops with one line."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from conftest import PROJECT_ROOT
from run_helpers import script_module

SCRIPT = PROJECT_ROOT / "speed" / "gpu_session.py"


@pytest.fixture(scope="module")
def session():
    with script_module(SCRIPT) as module:
        yield module


def test_sampler_and_training_sections_on_tiny_sizes(session, tmp_path):
    assert session.main(["--device", "cpu", "--quick", "--out", str(tmp_path),
                         "--sections", "tests", "sampler", "training"]) == 0
    figures = json.loads((tmp_path / "gpu-session.json").read_text())
    assert figures["machine"]["torch"] == torch.__version__ and figures["machine"]["gpu"] is None
    assert len(figures["tree"]["commit"]) == 40
    # the page beside the JSON, rewritten with it (speed/gpu_figures.py)
    page = (tmp_path / "gpu.md").read_text()
    assert "## GPU session" in page and "- quick: tiny sizes" in page
    assert f"- tree: `{figures['tree']['commit'][:12]}`" in page
    assert "| raft training step |" in page and "No gpu-check.json yet." in page
    sections = figures["sections"]
    assert sections["tests"] == {"skipped": "no CUDA device"}
    rows = sections["sampler"]["rows"]
    assert [r["preset"] for r in rows] == ["snow", "rain", "sparks", "snow-light"]
    assert all(r["same_count"] and r["identical_particles"] == 1.0 for r in rows)  # CPU: same bytes
    whats = [r["what"] for r in sections["training"]["rows"]]
    assert whats[0] == "raft training step"
    assert sum("sampled on the device" in w for w in whats) == 3
    assert all(r["seconds"] > 0 for r in sections["training"]["rows"])


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is here: the session would run")
def test_without_cuda_it_says_so_in_one_line(tmp_path):
    done = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
    assert "no CUDA device" in done.stderr
