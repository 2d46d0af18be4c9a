"""`weathergen attack --model NAME` and `weathergen evaluate --model NAME` for the networks whose
own test modules run no such command (RAFT, SpyNet and the FlowNets), on a tiny Sintel-format pair with
random-weight checkpoints written here (plumbing and agreement between the two commands, not
accuracy); and a check that every registered network is run by some command-line test."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner

from conftest import PROJECT_ROOT, write_fake_sintel
from weathergen.models import available_models, build_model

#: Networks whose attack and evaluate commands are run here.
HERE = ["raft", "spynet", "flownetc", "flownetcrobust", "flownet2"]
#: Networks whose commands other modules run.
ELSEWHERE = {"raft-small": "tests/attack/test_attack_cli.py",
             "gma": "tests/models/test_models_gma.py",
             "flowformer": "tests/models/test_models_flowformer.py"}


def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def tiny_sintel(tmp_path_factory):
    """One 40x56 frame pair (an odd size for every network's padding multiple)."""
    root = write_fake_sintel(tmp_path_factory.mktemp("sintel"), scenes=("alley",), frames=2,
                             size=(40, 56))
    return ["--dataset", "sintel", "--root", root, "--scenes", "alley", "--frames-per-scene", "1"]


def test_every_registered_network_is_run_by_a_command_line_test():
    # the paper's six, RAFT-small, and no network without a command-line test
    assert set(available_models()) == set(HERE) | set(ELSEWHERE)
    for name, path in ELSEWHERE.items():
        text = (PROJECT_ROOT / path).read_text()
        assert f'"--model", "{name}"' in text and '"evaluate"' in text and '"attack"' in text, path


@pytest.mark.slow
@pytest.mark.parametrize("name", HERE)
def test_attack_then_evaluate_with_every_network(name, tiny_sintel, tmp_path):
    torch.manual_seed(0)
    weights = tmp_path / f"{name}.pth"
    torch.save(build_model(name).network.state_dict(), weights)
    model = ["--model", name, "--checkpoint", weights, *(["--iters", "1"] if name == "raft" else [])]
    out = tmp_path / "snow"
    attacked = invoke(["attack", *model, *tiny_sintel, "--steps", "1", "--set", "count=40",
                       "--seed", "1", "--out", out, "--quiet"])
    assert attacked.exit_code == 0, attacked.output
    summary = json.loads((out / "summary.json").read_text())
    manifest = json.loads((out / "manifest.json").read_text())
    assert summary["pairs"] == 1 and manifest["config"]["model"]["name"] == name

    evaluated = invoke(["evaluate", "--weather", out, *model, "--json", tmp_path / "eval.json"])
    assert evaluated.exit_code == 0, evaluated.output
    result = json.loads((tmp_path / "eval.json").read_text())
    (row,) = result["pairs"]
    assert result["model"] == name
    # Both measure the written 8-bit frames with the same network.
    assert row["aee_weather"] == pytest.approx(summary["aee_adversarial"], rel=1e-4, abs=1e-5)

