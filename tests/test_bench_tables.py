"""speed/bench_tables.py: the paper's table counts, the hours arithmetic of ``--dry-run``,
and a measurement on tiny sizes on the CPU (its figures mean nothing; the code path is the GPU's)."""

from __future__ import annotations

import dataclasses
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


def test_precisions_that_do_not_apply_are_refused(bt, monkeypatch):
    assert bt.precision_settings("gma", "paper", "cpu") == "float32"   # CPU: no autocast
    assert bt.precision_settings("gma", "paper", "cuda") == "fp16"     # the paper's GMA
    assert bt.precision_settings("raft", "float32", "cpu") == "float32"
    assert bt.precision_settings("raft", "amp", "cuda") == "fp16"
    assert bt.precision_settings("gma", "bf16", "cpu") == "bf16"   # autocast on the CPU
    with pytest.raises(ValueError, match="refused for 'flowformer'"):   # beyond its bound
        bt.precision_settings("flowformer", "bf16", "cuda")
    for precision in ("amp", "tf32"):
        with pytest.raises(ValueError, match="CUDA"):
            bt.precision_settings("raft", precision, "cpu")
    with pytest.raises(ValueError, match="no mixed-precision mode"):
        bt.precision_settings("spynet", "amp", "cuda")
    from weathergen.models import model_spec, registry
    monkeypatch.setitem(registry._ARCHITECTURES, "spynet", dataclasses.replace(
        model_spec("spynet"), refused_precisions=("fp16",)))
    with pytest.raises(ValueError, match="refused for 'spynet'"):
        bt.precision_settings("spynet", "fp16", "cuda")


def session_file(tmp_path):
    """A GPU session's JSON: raft in its paper precision (float32) and amp (fp16), gma in its
    paper precision (fp16) and float32, and a row with options (not counted)."""
    def row(network, precision, attack, options="-"):
        return {"network": network, "precision": precision, "options": options,
                "attack": attack, "forward": 2 * attack, "best_batch": 4}

    data = {"machine": {"gpu": "GPU X"},
            "sections": {"tables": {"measured": [row("raft", "paper", 10.0), row("gma", "paper", 8.0),
                                                 row("gma", "float32", 5.0)]},
                         "options": {"rows": [row("raft", "amp", 20.0),
                                              row("raft", "float32", 99.0, "checkpointing"),
                                              {"network": "raft", "precision": "tf32",
                                               "options": "-", "skipped": "deadline"}]}}}
    path = tmp_path / "gpu-session.json"
    path.write_text(json.dumps(data))
    return path


def bench_file(tmp_path, fractions):
    line = "figures: " + json.dumps({**{n: {"step_fraction": f, "weights": "shipped checkpoint"}
                                        for n, f in fractions.items()},
                                     "spynet": {"step_fraction": 0.1, "weights": "random weights"}})
    data = {"sections": {"python speed/bench_early_stop.py": {"output": f"a table\n{line}\n"}}}
    path = tmp_path / "bench.json"
    path.write_text(json.dumps(data))
    return path


def test_session_throughputs_by_the_precision_they_set(bt, tmp_path):
    tps = bt.session_throughputs(session_file(tmp_path))
    assert {p: sorted(t) for p, t in tps.items()} == {"float32": ["gma", "raft"],
                                                      "fp16": ["gma", "raft"]}
    assert tps["float32"]["raft"].attack == 10.0 and tps["fp16"]["raft"].attack == 20.0
    assert tps["fp16"]["gma"].attack == 8.0 and tps["fp16"]["gma"].forward == 16.0
    assert bt.step_fractions(bench_file(tmp_path, {"raft": 0.5})) == {"raft": 0.5}
    assert bt.step_fractions(tmp_path / "missing.json") == {}


def test_hours_per_precision_with_and_without_early_stopping(bt, tmp_path):
    runs = [bt.Run("2", "clean flow", 100, 1, backward=False),
            bt.Run("4", "snow", 10, 36, stoppable=True), bt.Run("5", "pcfa", 10, 20)]
    tps = bt.session_throughputs(session_file(tmp_path))
    rows = bt.precision_hours(runs, tps, {"raft": 0.5, "gma": 0.25})
    raft = next(r for r in rows if r["network"] == "raft" and r["precision"] == "fp16")
    assert raft["table4"] == pytest.approx(360 / 20.0 / 3600)
    assert raft["table4_early"] == pytest.approx(0.5 * 360 / 20.0 / 3600)
    # the forward-only and the Lp runs are not shortened by early stopping
    assert raft["total"] == pytest.approx((100 / 40.0 + 360 / 20.0 + 200 / 20.0) / 3600)
    assert raft["total_early"] == pytest.approx((100 / 40.0 + 180 / 20.0 + 200 / 20.0) / 3600)
    gma = next(r for r in rows if r["network"] == "gma" and r["precision"] == "float32")
    assert gma["table4_early"] == pytest.approx(0.25 * 360 / 5.0 / 3600)
    # a network without a measured fraction takes the mean of the measured ones
    mean = bt.precision_hours(runs, {"fp16": {"spynet": bt.Throughput(10.0)}}, {"a": 0.2, "b": 0.6})
    assert mean[0]["step_fraction"] == pytest.approx(0.4) and not mean[0]["measured_fraction"]
    best = bt.fastest(rows)
    assert best["raft"]["precision"] == "fp16" and best["gma"]["precision"] == "fp16"
    text = bt.precision_report(rows, target_hours=1.0)
    t4 = 360 / 20.0 / 3600 + 360 / 8.0 / 3600
    assert f"Table 4 takes {t4:.1f} GPU-hours" in text and "| raft | fp16 | 20.00 |" in text


def test_from_figures_is_one_command(tmp_path):
    out = tmp_path / "hours.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--from-figures", "--session", str(session_file(tmp_path)),
         "--figures", str(tmp_path / "none.json"), "--bench", str(bench_file(tmp_path, {"raft": 0.5})),
         "--json", str(out)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    figures = json.loads(out.read_text())["from_figures"]
    assert figures["step_fractions"] == {"raft": 0.5}
    rows = {(r["network"], r["precision"]): r for r in figures["rows"]}
    assert rows["raft", "fp16"]["table4"] == pytest.approx(345_460 / 20.0 / 3600)
    assert rows["gma", "fp16"]["table4_early"] == pytest.approx(0.5 * 345_460 / 8.0 / 3600)
    assert "not measured on this tree" in done.stdout and "x the goal of 4 hours" in done.stdout
    assert figures["not_measured"]["raft"] == ["tf32", "bf16"]
