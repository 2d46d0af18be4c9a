"""The GPU figures page (docs/figures/gpu.md), written by speed/gpu_figures.py from the JSON files
of `make gpu-check` and of the GPU session: each section names its machine and tree, and what the
page derives from the figures (milliseconds per pair-step, GPU-hours at a rate, shares, gains) is
the arithmetic worked out by hand below."""

from __future__ import annotations

import copy
import json

import pytest

from conftest import PROJECT_ROOT
from run_helpers import script_module

SCRIPT = PROJECT_ROOT / "speed" / "gpu_figures.py"
FOLDER = PROJECT_ROOT / "docs" / "figures"


@pytest.fixture(scope="module")
def gf():
    with script_module(SCRIPT) as module:
        yield module


MACHINE = {"torch": "2.9.0+cu128", "python": "3.12.0", "host": "box", "cpus": 8,
           "gpu": "Test GPU", "gpu_memory_gib": 80.0, "cuda": "12.8"}


def measured(network, rate, batch, share, forward, stop, memory, precision="paper"):
    return {"network": network, "precision": precision, "options": "-",
            "batches": {str(batch): {"step_seconds": batch / rate, "pair_steps_per_second": rate,
                                     "memory_gib": memory}},
            "best_batch": batch, "attack": rate, "network_share": share, "forward": forward,
            "stop": stop, "seconds": 1.0}


# Table 2: 3600 forward passes per network; Table 4: 36,000 pair-steps per network.
# fast: 10 pair-steps/s, 30 pairs/s forward -> Table 2 3600 / 30 / 3600 = 1/30 h, Table 4
# 36000 / 10 / 3600 = 1.0 h; slow: 2 and 6 -> 1/6 h and 5.0 h. The target of 3 h allows
# 3 * 3600 / 36000 = 0.3 s = 300 ms per pair-step summed; fast takes 100 ms, slow 500 ms.
HOURS = {"fast": {"2": 1 / 30, "4": 1.0, "total": 1 / 30 + 1.0},
         "slow": {"2": 1 / 6, "4": 5.0, "total": 1 / 6 + 5.0},
         "all": {"2": 0.2, "4": 6.0, "total": 6.2}}
SESSION = {
    "machine": MACHINE, "tree": {"commit": "0123456789abcdef" * 2 + "01234567", "dirty": True},
    "quick": False, "elapsed_s": 300.4,
    "sections": {
        "tests": {"returncode": 0, "tail": ["....", "4 passed, 10 deselected in 3.00s"]},
        "tables": {
            "measured": [measured("fast", 10.0, 4, 0.9, 30.0, "largest batch size tried", 4.0),
                         measured("slow", 2.0, 1, 0.98, 6.0, "out of memory at batch 2", 20.0)],
            "counts": {"2": {"pair_steps": 0, "forward_passes": 3600},
                       "4": {"pair_steps": 36000, "forward_passes": 0}},
            "hours": {"paper": {
                "throughput": {"fast": {"attack": 10.0, "forward": 30.0, "source": "measured, paper, batch 4"},
                               "slow": {"attack": 2.0, "forward": 6.0, "source": "measured, paper, batch 1"}},
                "hours": HOURS, "target_hours_table4": 3.0,
                "table4_ms_per_pair_step_allowed": 300.0, "table4_ms_per_pair_step_summed": 600.0}}},
        "options": {"rows": [
            dict(measured("fast", 12.5, 4, 0.9, 35.0, "largest batch size tried", 3.0, "amp"),
                 flow_difference={"max_px": 0.01, "rms_px": 0.002, "flow_rms_px": 2.5}),
            {"network": "slow", "precision": "tf32", "options": "compile=default",
             "skipped": "deadline"}]},
        "sampler": {"rows": [{"preset": "snow", "count": 3000, "cpu_s": 0.05, "device_s": 0.02,
                              "same_count": True, "identical_particles": 1.0}]},
        "training": {"rows": [
            {"what": "raft training step", "seconds": 0.2},
            {"what": "weather of a batch of 6: snow, sampled on the device", "seconds": 0.05,
             "share_of_training_step": 0.25}]},
    }}


def row(area, what, seconds, memory=None, note="", failed=False):
    return {"area": area, "what": what, "seconds": seconds, "memory_gib": memory, "note": note,
            "failed": failed}


CHECK = {
    "title": "gpu-check on Test GPU, torch 2.9.0+cu128, 1024x436", "machine": MACHINE,
    "tree": {"commit": "fedcba9876543210" * 2 + "fedcba98", "dirty": False},
    "rows": [row("training", "weather of a batch of 6: snow", 0.1, 1.5),
             row("training", "raft training step, batch of 6 368x768", 0.4, 14.0),
             row("attack batch", "raft, batch of 1: a step", 0.1, 3.0, "10.00 pair-steps/s"),
             row("attack batch", "raft, batch of 4: a step", 0.2, 6.0, "20.00 pair-steps/s"),
             row("networks", "raft, forward", 0.05, 0.5),
             row("networks", "raft, forward + backward", 0.125, 3.5),
             row("render", "snow (3000), forward", None, None, "RuntimeError: boom", True)]}


def test_the_session_section_names_its_machine_and_tree_and_works_out_the_tables(gf):
    lines = gf.page(None, SESSION).splitlines()
    assert "- machine: Test GPU (80.0 GiB), CUDA 12.8, torch 2.9.0+cu128, Python 3.12.0, 8 CPUs, " \
           "host box" in lines
    assert "- tree: `0123456789ab` with uncommitted changes" in lines
    assert "`pytest -m cuda -k \"sampling_on or fields_views\"`: exit status 0, 4 passed, " \
           "10 deselected in 3.00s" in lines
    # ms per pair-step = 1000 / rate
    assert "| fast | paper | - | 4 | 10.00 | 100.0 | 90 % | 30.00 | 4.0 | 4: 10.00 | " \
           "largest batch size tried |" in lines
    assert "| slow | paper | - | 1 | 2.00 | 500.0 | 98 % | 6.00 | 20.0 | 1: 2.00 | " \
           "out of memory at batch 2 |" in lines
    # hours per table; share of the total: 1.0333 / 6.2 = 17 %, 5.1667 / 6.2 = 83 %
    assert "| fast | 10.00 (measured, paper, batch 4) | 0.0 | 1.0 | **1.0** | 17 % |" in lines
    assert "| slow | 2.00 (measured, paper, batch 1) | 0.2 | 5.0 | **5.2** | 83 % |" in lines
    assert "| **all 2** |  | 0.2 | 6.0 | **6.2** | 100 % |" in lines
    # 600 / 300 = 2.0x; slow 500 / 300 = 1.7x; the other 600 - 500 = 100 ms, 6.0 - 5.0 = 1.0 h
    assert ("Table 4 (36,000 pair-steps per network): 6.0 GPU-hours for these 2 network(s). The "
            "target of 3 hours allows 300.0 ms per pair-step summed over the networks; they take "
            "600.0 ms, 2.0x the target. The slowest, slow, takes 500.0 ms per pair-step (5.0 h of "
            "Table 4, 1.7x the whole allowance); the other 1 together 100.0 ms (1.0 h, 0.3x the "
            "allowance).") in lines
    # an option: 12.5 / 10 = 1.25x its float32 (here its paper row); Table 4 at 12.5 pair-steps/s:
    # 36000 / 12.5 / 3600 = 0.8 h
    assert "| fast | amp | - | 4 | 12.50 | 1.25x | 3.0 | 0.0100 / 0.0020 (2.50) | 0.8 | " \
           "largest batch size tried |" in lines
    assert "| slow | tf32 | compile=default | – | – | – | – | – | – | skipped (deadline) |" in lines
    assert "| snow | 3000 | 50.0 | 20.0 | 100 % |" in lines
    assert "| raft training step | 0.200 | – |" in lines
    assert "| weather of a batch of 6: snow, sampled on the device | 0.050 | 25 % |" in lines
    assert "No gpu-check.json yet." in lines


def test_table4_pair_steps_follow_from_the_allowance_when_the_counts_are_missing(gf):
    tables = copy.deepcopy(SESSION["sections"]["tables"])
    assert gf.table4_pair_steps(tables) == 36000
    del tables["counts"]
    assert gf.table4_pair_steps(tables) == 36000        # 3 h * 3600 s / 0.3 s


def test_the_check_section_has_a_table_per_area_with_shares_and_gains(gf):
    lines = gf.page(CHECK, None).splitlines()
    assert "gpu-check on Test GPU, torch 2.9.0+cu128, 1024x436" in lines
    assert "- tree: `fedcba987654`" in lines
    assert "No gpu-session.json yet." in lines
    assert [x for x in lines if x.startswith("### ")] == ["### training", "### attack batch",
                                                         "### networks", "### render"]
    assert "| weather of a batch of 6: snow | 0.100 | 1.50 | 25 % |  |" in lines    # 0.1 / 0.4
    assert "| raft training step, batch of 6 368x768 | 0.400 | 14.00 | – |  |" in lines
    # 4 / 0.2 = 20 pair-steps/s against 1 / 0.1 = 10
    assert "| raft, batch of 4: a step | 0.200 | 6.00 | 2.00x | 20.00 pair-steps/s |" in lines
    assert "| raft | 0.050 | 0.50 | 0.125 | 3.50 | 8.0 |  |" in lines                  # 1 / 0.125
    assert "| snow (3000), forward | – | – | FAILED: RuntimeError: boom |" in lines


def test_a_json_without_machine_or_tree_says_so(gf):
    old = {"title": "gpu-check on X", "rows": [row("render", "snow (3000), forward", 0.02, 0.3)]}
    lines = gf.page(old, {"machine": MACHINE, "sections": {"tables": {"skipped": "deadline"}}}).splitlines()
    assert lines.count("- tree: not recorded in this JSON file") == 2
    assert "Skipped (deadline)." in lines


def test_the_command_writes_the_page_of_a_folder(gf, tmp_path):
    (tmp_path / "gpu-check.json").write_text(json.dumps(CHECK))
    (tmp_path / "gpu-session.json").write_text(json.dumps(SESSION))
    assert gf.main([str(tmp_path)]) == 0
    assert (tmp_path / "gpu.md").read_text() == gf.page(CHECK, SESSION)
    assert gf.main([str(tmp_path / "none")]) == 2


def test_the_committed_page_is_the_committed_json_rendered(gf):
    """Nobody edits gpu.md by hand: after copying a JSON file in, `python speed/gpu_figures.py`."""
    check = json.loads((FOLDER / "gpu-check.json").read_text())
    session = json.loads((FOLDER / "gpu-session.json").read_text())
    text = (FOLDER / "gpu.md").read_text()
    assert text == gf.page(check, session), "rewrite it: python speed/gpu_figures.py"
    assert "- machine: NVIDIA" in text and "CUDA" in text
