"""`weathergen attack --model NAME` and `weathergen evaluate --model NAME` for the networks whose
own test modules run no such command (RAFT, both SpyNets and the FlowNets), on a tiny Sintel-format pair with
random-weight checkpoints written here (plumbing and agreement between the two commands, not
accuracy); and a check that every registered network is run by some command-line test."""

from __future__ import annotations

import pytest
import torch
from model_checks import attack_then_evaluate, tiny_sintel

from conftest import PROJECT_ROOT
from weathergen.models import available_models, build_model

#: Networks whose attack and evaluate commands are run here.
HERE = ["raft", "spynet", "spynet-sniklaus", "flownetc", "flownetcrobust", "flownet2"]
#: Networks whose commands other modules run.
ELSEWHERE = {"raft-small": "tests/attack/test_attack_cli.py",
             "gma": "tests/models/test_models_gma.py",
             "flowformer": "tests/models/test_models_flowformer.py"}


@pytest.fixture(scope="module")
def sintel_options(tmp_path_factory):
    return tiny_sintel(tmp_path_factory.mktemp("sintel"))


def test_every_registered_network_is_run_by_a_command_line_test():
    # the paper's six, RAFT-small, and no network without a command-line test
    assert set(available_models()) == set(HERE) | set(ELSEWHERE)
    for name, path in ELSEWHERE.items():
        text = (PROJECT_ROOT / path).read_text()
        runs_both = ("attack_then_evaluate(" in text
                     or ('"evaluate"' in text and '"attack"' in text))
        assert f'"--model", "{name}"' in text and runs_both, path


@pytest.mark.slow
@pytest.mark.parametrize("name", HERE)
def test_attack_then_evaluate_with_every_network(name, sintel_options, tmp_path):
    torch.manual_seed(0)
    weights = tmp_path / f"{name}.pth"
    torch.save(build_model(name).network.state_dict(), weights)
    model = ["--model", name, "--checkpoint", weights, *(["--iters", "1"] if name == "raft" else [])]
    summary, manifest, result = attack_then_evaluate(model, sintel_options, tmp_path)
    assert summary["pairs"] == 1 and manifest["config"]["model"]["name"] == name
    (row,) = result["pairs"]
    assert result["model"] == name
    # Both measure the written 8-bit frames with the same network.
    assert row["aee_weather"] == pytest.approx(summary["aee_adversarial"], rel=1e-4, abs=1e-5)

