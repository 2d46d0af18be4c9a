"""examples/finetune_raft_small.py: fine-tuning RAFT-small with 50 % snowy pairs lowers the loss."""

from __future__ import annotations

import importlib.util

from conftest import PROJECT_ROOT


def load_example():
    path = PROJECT_ROOT / "examples" / "finetune_raft_small.py"
    spec = importlib.util.spec_from_file_location("finetune_raft_small", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_finetuning_on_the_demo_scene_lowers_the_loss(tmp_path, demo_root, capsys):
    example = load_example()
    # the checkpoint by name, as the README gives it: the released weights shipped with the package
    result = example.main(["--checkpoint", "raft-small", "--steps", "8", "--batch-size", "2",
                           "--crop", "64", "128", "--iters", "4", "--lr", "4e-4",
                           "--set", "count=200", "--eval-pairs", "2", "--workers", "0",
                           "--out", str(tmp_path / "run")])
    log = result["log"]
    assert [r["step"] for r in log] == list(range(1, 9))
    assert sum(r["weather"] for r in log) > 0                 # some pairs were snowy
    before, after = result["before"], result["after"]
    assert after["weather"]["loss"] < before["weather"]["loss"]
    assert after["clean"]["loss"] < before["clean"]["loss"]
    assert (tmp_path / "run" / "raft-small-finetuned.pth").is_file()
    assert (tmp_path / "run" / "log.csv").read_text().count("\n") == 9
    assert "before:" in capsys.readouterr().out
