"""speed/bench_tables.py: the paper's table counts, the hours arithmetic of ``--dry-run``,
and a measurement on tiny sizes on the CPU (its figures mean nothing; the code path is the GPU's)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch

from conftest import PROJECT_ROOT
from run_helpers import script_module

SCRIPT = PROJECT_ROOT / "speed" / "bench_tables.py"


@pytest.fixture(scope="module")
def bt():
    with script_module(SCRIPT) as module:
        yield module


def test_the_counts_are_the_papers(bt):
    runs = bt.paper_runs()
    counts = bt.table_counts(runs)
    # Table 2: 19 random-weather configurations and the clean flow, forward only, Sintel train.
    assert sorted(r.label for r in runs if r.table == "2")[:3] == ["additive-blue",
                                                                   "additive-color",
                                                                   "additive-green"]
    assert counts["2"] == {"pair_steps": 0, "forward_passes": 20 * 1041}
    # Table 3: seven grey configurations, Table 4: four weathers, 750 steps + step 0, tr115.
    assert counts["3"] == {"pair_steps": 7 * 115 * 751, "forward_passes": 0}
    assert counts["4"] == {"pair_steps": 345_460, "forward_passes": 0}
    # Table 5 on Sintel train: PCFA 20 L-BFGS steps of up to 10 evaluations, I-FGSM 25, snow 750.
    assert counts["5"]["pair_steps"] == 1041 * (201 + 26 + 751)


def test_hours_are_pair_steps_over_throughput(bt):
    runs = bt.paper_runs()
    h = bt.table_hours(runs, bt.Throughput(attack=10.0, forward=20.0))
    assert h["4"] == pytest.approx(345_460 / 10 / 3600)
    assert h["2"] == pytest.approx(20 * 1041 / 20 / 3600)
    assert h["total"] == pytest.approx(h["2"] + h["3"] + h["4"] + h["5"])
    # no forward throughput: forward passes count at the attack's (an upper bound)
    assert bt.table_hours(runs, bt.Throughput(10.0))["2"] == pytest.approx(20 * 1041 / 10 / 3600)
    both = bt.all_hours(runs, {"a": bt.Throughput(10.0, 20.0), "b": bt.Throughput(5.0, 20.0)})
    assert both["all"]["4"] == pytest.approx(345_460 / 10 / 3600 + 345_460 / 5 / 3600)
    # 4 hours for 345,460 pair-steps: 41.7 ms per pair-step summed over the networks
    assert 1 / bt.needed_for(4.0, 345_460) == pytest.approx(4 * 3600 / 345_460)


def test_throughputs_from_a_figures_file_and_from_the_command_line(bt, tmp_path):
    rows = [{"area": "attack batch", "what": "raft, batch of 1: a step", "seconds": 0.1},
            {"area": "attack batch", "what": "raft, batch of 8: a step", "seconds": 0.4},
            {"area": "networks", "what": "raft, forward", "seconds": 0.05},
            {"area": "networks", "what": "gma, forward + backward", "seconds": 0.05},
            {"area": "networks", "what": "gma, forward", "seconds": 0.025},
            {"area": "networks", "what": "flowformer, forward + backward", "seconds": None,
             "failed": True}]
    path = tmp_path / "gpu-check.json"
    path.write_text(json.dumps({"title": "t", "rows": rows}))
    tps = bt.figures_throughputs(path)
    assert set(tps) == {"raft", "gma"}
    assert tps["raft"].attack == pytest.approx(20.0) and tps["raft"].forward == pytest.approx(20.0)
    assert tps["gma"].attack == pytest.approx(20.0) and tps["gma"].forward == pytest.approx(40.0)
    given = bt.parse_assume(["raft=36.1", "flowformer=3/9"])
    assert given["raft"].attack == 36.1 and given["raft"].forward is None
    assert given["flowformer"].forward == 9.0
    for bad in ("raft", "raft=0", "raft=x", "raft=3/-1"):
        with pytest.raises(ValueError, match="--assume"):
            bt.parse_assume([bad])


def test_dry_run_prints_the_hours_and_writes_them(tmp_path):
    out = tmp_path / "tables.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--dry-run", "--models", "raft", "gma", "--assume",
         "raft=36", "gma=18/50", "--figures", str(tmp_path / "none.json"), "--json", str(out)],
        capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    figures = json.loads(out.read_text())
    hours = figures["dry_run"]["hours"]
    assert hours["raft"]["4"] == pytest.approx(345_460 / 36 / 3600)
    assert hours["all"]["4"] == pytest.approx(345_460 * (1 / 36 + 1 / 18) / 3600)
    assert "| all networks |" in done.stdout and f"{hours['all']['total']:.1f}" in done.stdout
    missing = subprocess.run([sys.executable, str(SCRIPT), "--dry-run", "--models", "raft",
                              "--figures", str(tmp_path / "none.json")],
                             capture_output=True, text=True, timeout=300)
    assert missing.returncode == 2 and "no throughput for raft" in missing.stderr


def test_the_hours_report_of_each_measured_precision(bt, capsys):
    """What bench_tables.py and the GPU session print and keep: per precision measured, the
    hours of every table at the best throughput (a float32 row stands in for the paper's)."""
    runs = [bt.Run("2", "clean flow", 100, 1, backward=False), bt.Run("4", "snow", 10, 36)]
    results = [bt.Measured("raft", "float32", "-", best_batch=8, attack=2.0, forward=5.0),
               bt.Measured("gma", "paper", "-", best_batch=4, attack=4.0, forward=10.0),
               bt.Measured("gma", "float32", "-", best_batch=4, attack=3.0),
               bt.Measured("spynet", "paper", "-", stop="failed: boom")]
    hours = bt.report_hours(runs, results, ["paper", "float32", "tf32"], "GPU-hours on X")
    assert list(hours) == ["paper", "float32"]              # nothing measured in tf32
    paper = hours["paper"]["hours"]
    assert set(paper) == {"raft", "gma", "all"}
    assert paper["raft"]["4"] == pytest.approx(360 / 2.0 / 3600)   # 10 pairs x 36 pair-steps
    assert paper["raft"]["2"] == pytest.approx(100 / 5.0 / 3600)   # forward passes, forward rate
    assert paper["gma"]["total"] == pytest.approx((100 / 10.0 + 360 / 4.0) / 3600)
    assert hours["float32"]["hours"]["gma"]["4"] == pytest.approx(360 / 3.0 / 3600)
    printed = capsys.readouterr().out
    assert "GPU-hours on X, paper" in printed and "GPU-hours on X, float32" in printed


TINY = dict(width=64, height=32, iters=1, count=20, batch_sizes=(1, 2), steps=1)


def test_a_measurement_on_tiny_sizes_finds_a_best_batch(bt):
    bench = bt.Bench("cpu", bt.Sizes(**TINY))
    r = bt.measure(bench, "raft-small", "paper")
    assert set(r.batches) <= {1, 2} and 1 in r.batches
    assert r.best_batch in r.batches and r.attack == max(
        v["pair_steps_per_second"] for v in r.batches.values())
    assert r.forward > 0 and r.network_share > 0 and r.stop
    tps = bt.best_throughputs([r], "paper")
    assert tps["raft-small"].attack == r.attack


def test_out_of_memory_ends_the_batch_sizes(bt, monkeypatch):
    bench = bt.Bench("cpu", bt.Sizes(**TINY))
    real = bt.Bench.step

    def step(self, model, batch):
        if batch == 2:
            raise torch.cuda.OutOfMemoryError("CUDA out of memory. Tried to allocate 2 GiB")
        return real(self, model, batch)

    monkeypatch.setattr(bt.Bench, "step", step)
    r = bt.measure(bench, "raft-small", "float32")
    assert r.best_batch == 1 and list(r.batches) == [1]
    assert r.stop == "out of memory at batch 2"


def test_precisions_that_do_not_apply_are_refused(bt):
    assert bt.precision_settings("gma", "paper", "cpu") == (False, False)   # CPU: no autocast
    assert bt.precision_settings("raft", "float32", "cpu") == (False, False)
    with pytest.raises(ValueError, match="CUDA"):
        bt.precision_settings("raft", "amp", "cpu")
