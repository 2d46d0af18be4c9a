"""``--precision`` and ``--early-stop`` on the command line: refused combinations in one line
before anything runs, and an attack that records both."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

ONE_PAIR = ["--scenes", "courtyard", "--frames-per-scene", "1"]


def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


@pytest.mark.parametrize("args, message", [
    (["--precision", "bf16", "--amp"], "--precision and --amp are exclusive"),
    (["--model", "flowformer", "--precision", "bf16"],
     "--precision bf16 is refused for 'flowformer': its flow differs from float32's"),
    (["--precision", "tf32"], "--precision tf32 needs a CUDA device"),
    (["--early-stop", "5"], "--early-stop must be WINDOW:TOL"),
    (["--early-stop", "5:0.1", "--compat", "reference"],
     "--early-stop does not apply under --compat reference"),
    (["--early-stop", "5:0.1", "--method", "pcfa"], "--early-stop applies to the weather attack only"),
])
def test_refused_before_anything_runs(tmp_path, args, message):
    out = tmp_path / "out"
    result = invoke(["attack", *ONE_PAIR, "--steps", "1", "--out", out, *args])
    assert result.exit_code == 2 and message in result.output, result.output
    assert not out.exists()


def test_evaluate_and_benchmark_refuse_a_precision_the_network_refuses(tmp_path):
    result = invoke(["benchmark", "--networks", "flowformer", "--precision", "bf16",
                     "--out", tmp_path / "bench"])
    assert result.exit_code == 2 and "refused for 'flowformer'" in result.output, result.output
    result = invoke(["evaluate", "--weather", tmp_path, "--model", "flowformer", "--precision", "bf16"])
    assert result.exit_code == 2 and "refused for 'flowformer'" in result.output, result.output


@pytest.mark.slow
def test_an_attack_records_its_precision_and_early_stopping(tmp_path, raft_small_weights):
    out = tmp_path / "snow"
    result = invoke(["attack", "--model", "raft-small", "--checkpoint", raft_small_weights,
                     "--iters", "2", *ONE_PAIR, "--steps", "6", "--set", "count=150",
                     "--precision", "bf16", "--early-stop", "1:0.5", "--out", out])
    assert result.exit_code == 0, result.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["model"]["precision"] == "bf16"
    assert manifest["config"]["model"]["amp"] is True
    assert manifest["config"]["attack"]["early_stop"] == "1:0.5"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["precision"] == "bf16"
    # no step lowers the loss by half: the pair ends after one window, its best step kept
    from weathergen.outputs.attack import read_log

    rows = read_log(out / "training" / "attack_log" / "courtyard_0001.csv")
    assert [r["step"] for r in rows] == [0, 1]
