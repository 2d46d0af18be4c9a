"""Scores people can compare: RobustSpring's robust EPE, Fl and 1px of the weather flow against the
clean flow (checked by hand on a small field), the settings record that every table, JSON and
CSV carries, and a severity ladder whose adversarial rung falls below its random one marked."""

from __future__ import annotations

import hashlib

import pytest
import torch

from weathergen.attack.figures import mean_figures, region_figures
from weathergen.attack.record import SETTINGS_KEYS, run_settings, settings_text


def test_robust_epe_fl_and_1px_by_hand():
    clean = torch.zeros(1, 2, 2, 2)
    clean[0, 0] = torch.tensor([[100.0, 0.0], [10.0, 2.0]])       # u; v stays 0
    weather = clean.clone()
    # errors: (3, 4) -> 5 px against |f| = 100 (5 % = 5: not above, not Fl); 0.5 px;
    # 4 px against |f| = 10 (above 3 and 0.5: Fl); 3 px exactly against |f| = 2 (not above 3)
    weather[0, :, 0, 0] += torch.tensor([3.0, 4.0])
    weather[0, 0, 0, 1] += 0.5
    weather[0, 1, 1, 0] += 4.0
    weather[0, 0, 1, 1] += 3.0
    out = region_figures(clean, weather)
    assert out["robust_epe"] == pytest.approx((5 + 0.5 + 4 + 3) / 4)
    assert out["robust_fl"] == pytest.approx(25.0)                # the 4 px error alone
    assert out["robust_1px"] == pytest.approx(75.0)               # 5, 4 and 3 px
    assert out["robust_epe"] == pytest.approx(out["aee_clear_px"])    # AEE(f, f̌), nothing covered
    rows = [out, {**out, "robust_fl": 75.0, "robust_1px": 25.0, "robust_epe": 1.0}]
    means = mean_figures(rows)
    assert (means["robust_fl"], means["robust_1px"]) == (50.0, 50.0)
    assert means["robust_epe"] == pytest.approx((12.5 / 4 + 1.0) / 2)


def test_the_settings_record_and_its_line(tmp_path):
    weights = tmp_path / "w.pth"
    weights.write_bytes(b"weights")
    record = run_settings("raft", weights, iters=12, padding="even", steps=20,
                          learning_rates={"lr": 1e-5}, seed=3)
    assert tuple(record) == SETTINGS_KEYS
    digest = hashlib.sha256(b"weights").hexdigest()
    assert record["checkpoint_sha256"] == digest
    assert record["precision"] == "float32" and record["crop"] == "none"
    assert run_settings("raft", precision="fp16")["precision"] == "fp16"
    line = settings_text(record)
    for words in ("network raft", f"sha256 {digest[:12]}", "iters 12", "float32", "padding even",
                  "crop none", "20 steps", "lr 1e-05", "seed 3"):
        assert words in line
    assert "the network's default" in settings_text(run_settings("raft"))


def ladder_rows(adversarial_heavy: float) -> list[dict]:
    settings = run_settings("raft-small", iters=4, padding="even", steps=5,
                            learning_rates={"lr": 1e-5}, seed=0)
    return [{"network": "raft-small", "kind": "weather", "label": f"snow-{rung}",
             "epe_benign": 1.0, "aee_random": r, "epe_random": 2.0, "aee_adversarial": a,
             "epe_adversarial": 3.0, "settings": settings}
            for rung, r, a in (("light", 1.0, 2.0), ("moderate", 2.0, 4.0),
                               ("heavy", 8.31, adversarial_heavy))]


def test_a_ladder_marks_an_adversarial_rung_below_its_random_one():
    from weathergen.benchmark import ladder_curves, markdown_table
    from weathergen.benchmark.tables import latex_table, ladder_tables

    below = ladder_tables(ladder_curves(ladder_rows(6.98), ["snow"], ["raft-small"]),
                          ["raft-small"])[0]
    md = markdown_table(below, "c")
    assert "6.98†" in md and "8.31†" not in md and "4.00†" not in md
    assert "† adversarial below random (raft-small heavy)" in md
    assert r"6.98$^\dagger$" in latex_table(below, "c")
    above = ladder_tables(ladder_curves(ladder_rows(9.5), ["snow"], ["raft-small"]),
                          ["raft-small"])[0]
    assert "†" not in markdown_table(above, "c") and not above.note


def test_every_benchmark_table_carries_the_settings(demo_root, tmp_path):
    import csv
    import json

    from weathergen.benchmark import BenchmarkSpec
    from weathergen.benchmark.tables import write_tables
    from weathergen.datasets import open_dataset

    spec = BenchmarkSpec(open_dataset("demo", demo_root), tmp_path, ["raft-small"],
                         presets=(), lp_methods=(), ladders=("snow",))
    for row in ladder_rows(6.98):
        folder = tmp_path / "runs" / "raft-small" / row["label"]
        folder.mkdir(parents=True)
        (folder / "summary.json").write_text(json.dumps({**row, "pairs": 1}))
    paths = write_tables(spec)
    with open(paths["csv"], newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["iters"], r["precision"], r["padding"], r["crop"], r["steps"], r["seed"],
             r["learning_rates"]) for r in rows] == [("4", "float32", "even", "none", "5", "0",
                                                      "lr=1e-05")] * 3
    document = json.loads(paths["json"].read_text())
    assert all(r["settings"]["network"] == "raft-small" for r in document["rows"])
    line = "iters 4, float32, padding even, crop none, 5 steps, lr 1e-05, seed 0"
    assert line in paths["markdown"].read_text()
    assert line in paths["latex"].read_text()
    for table in (tmp_path / "tables").glob("*.md"):
        assert line in table.read_text(), table.name
    assert "6.98†" in paths["markdown"].read_text()
    for name in ("curves", "scores"):
        with open(paths[name], newline="") as fh:
            assert {(r["iters"], r["precision"], r["steps"]) for r in csv.DictReader(fh)} == \
                {("4", "float32", "5")}


@pytest.mark.slow
def test_attack_and_evaluate_write_the_robust_figures_and_the_settings(tmp_path,
                                                                       raft_small_weights):
    import json

    from click.testing import CliRunner

    from weathergen.cli.main import _register, cli

    _register()

    def invoke(args):
        return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)

    out = tmp_path / "a"
    attacked = invoke(["attack", "--model", "raft-small", "--checkpoint", raft_small_weights,
                       "--iters", "1", "--scenes", "courtyard", "--frames-per-scene", "1",
                       "--steps", "1", "--set", "count=40", "--seed", "5", "--out", out])
    assert attacked.exit_code == 0, attacked.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"]["steps"] == 1 and summary["settings"]["seed"] == 5
    assert summary["settings"]["learning_rates"] == {"positions": 1e-5, "color": 1e-5,
                                                     "transparency": 1e-5}
    assert summary["settings"]["checkpoint_sha256"] == hashlib.sha256(
        raft_small_weights.read_bytes()).hexdigest()
    assert summary["robust_epe"] == pytest.approx(summary["aee_adversarial"], rel=1e-5)
    assert 0 <= summary["robust_1px"] <= 100 and summary["robust_fl"] <= summary["robust_1px"]
    assert "Settings: network raft-small" in attacked.output and "RobustSpring" in attacked.output
    evaluated = invoke(["evaluate", "--weather", out, "--model", "raft-small", "--checkpoint",
                        raft_small_weights, "--iters", "1", "--json", tmp_path / "e.json"])
    assert evaluated.exit_code == 0, evaluated.output
    figures = json.loads((tmp_path / "e.json").read_text())
    assert figures["settings"]["iters"] == 1 and figures["settings"]["seed"] == 5
    assert figures["settings"]["steps"] is None and figures["settings"]["padding"] == "even"
    assert figures["summary"]["robust_epe"] == pytest.approx(summary["robust_epe"], rel=1e-4)
    assert "Settings: network raft-small" in evaluated.output
