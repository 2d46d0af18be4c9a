"""`weathergen attack` and `weathergen evaluate` with the networks added beside RAFT, on the
demo scene with random-weight checkpoints written here (speed and plumbing, not accuracy)."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner

ONE_PAIR = ["--scenes", "courtyard", "--frames-per-scene", "1"]


def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def random_checkpoint(arch, path):
    from weathergen.models import build_model

    torch.manual_seed(0)
    torch.save(build_model(arch).network.state_dict(), path)
    return path


def test_attack_then_evaluate_with_spynet(tmp_path):
    weights = random_checkpoint("spynet", tmp_path / "spynet.pth")
    out = tmp_path / "attack"
    result = invoke(["attack", "--model", "spynet", "--checkpoint", weights, *ONE_PAIR,
                     "--steps", "1", "--set", "count=60", "--seed", "3", "--out", out])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["pairs"] == 1 and summary["aee_adversarial"] is not None
    manifest = json.loads((out / "manifest.json").read_text())
    assert "spynet" in json.dumps(manifest)

    evaluated = invoke(["evaluate", "--weather", out, "--model", "spynet", "--checkpoint",
                        weights, "--json", tmp_path / "eval.json"])
    assert evaluated.exit_code == 0, evaluated.output
    (row,) = json.loads((tmp_path / "eval.json").read_text())["pairs"]
    # Both measure the written 8-bit frames with the same network.
    assert row["aee_weather"] == pytest.approx(summary["aee_adversarial"], rel=1e-4, abs=1e-5)


@pytest.mark.parametrize("arch", ["flownetcrobust"])
def test_evaluate_with_a_flownet(arch, tmp_path):
    weights = random_checkpoint(arch, tmp_path / f"{arch}.pth")
    weather = tmp_path / "snow"
    rendered = invoke(["render", "--preset", "snow", "--set", "count=200", *ONE_PAIR,
                       "--out", weather])
    assert rendered.exit_code == 0, rendered.output
    result = invoke(["evaluate", "--weather", weather, "--model", arch, "--checkpoint", weights,
                     "--json", tmp_path / "eval.json"])
    assert result.exit_code == 0, result.output
    (row,) = json.loads((tmp_path / "eval.json").read_text())["pairs"]
    assert row["aee_weather"] > 0.0  # the snow changes the random network's flow

