"""`weathergen benchmark` on the demo scene with RAFT-small and tiny settings: the tables hold
exactly the per-run summaries, shards split the grid, and a rerun resumes."""

from __future__ import annotations

import csv
import json

import pytest
from click.testing import CliRunner

pytestmark = pytest.mark.slow


def invoke(args):
    from weathergen.cli.main import cli

    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def grid_args(weights, out, *extra):
    return ["benchmark", "--networks", "raft-small", "--checkpoint", f"raft-small={weights}",
            "--presets", "snow", "--lp", "ifgsm", "--steps", "1", "--lp-steps", "1",
            "--iters", "2", "--set", "count=100", "--scenes", "courtyard", "--frames-per-scene",
            "1", "--out", out, *extra]


@pytest.fixture(scope="module")
def bench(tmp_path_factory, raft_small_weights):
    out = tmp_path_factory.mktemp("bench") / "b"
    # two shards: each runs its own cells; together they finish the grid
    first = invoke(grid_args(raft_small_weights, out, "--shard", "1/2", "--quiet"))
    assert first.exit_code == 0, first.output
    done = sorted(p.parent.name for p in (out / "runs").glob("*/*/summary.json"))
    assert done == ["snow"]                           # cell 1 of snow, ifgsm
    partial = json.loads((out / "results.json").read_text())
    assert [r["aee_adversarial"] is None for r in partial["rows"]] == [False, True]
    assert "| I-FGSM | – |" in (out / "tables.md").read_text()
    second = invoke(grid_args(raft_small_weights, out, "--shard", "2/2"))
    assert second.exit_code == 0, second.output
    return out, second.output


def summary(out, label):
    return json.loads((out / "runs" / "raft-small" / label / "summary.json").read_text())


def test_tables_equal_the_per_run_summaries(bench, raft_small_weights):
    out, output = bench
    snow, ifgsm = (summary(out, x) for x in ("snow", "ifgsm"))
    doc = json.loads((out / "results.json").read_text())
    rows = {r["label"]: r for r in doc["rows"]}
    for label, s in (("snow", snow), ("ifgsm", ifgsm)):
        for key in ("aee_random", "aee_adversarial", "target_initial", "target_adversarial"):
            assert rows[label][key] == s[key]
        assert rows[label]["pairs"] == 1
    with open(out / "results.csv", newline="") as fh:
        csv_rows = {r["label"]: r for r in csv.DictReader(fh)}
    assert float(csv_rows["ifgsm"]["aee_adversarial"]) == pytest.approx(ifgsm["aee_adversarial"])
    # network and checkpoint recorded
    (net,) = doc["networks"]
    assert net["network"] == "raft-small" and net["checkpoint"] == str(raft_small_weights)
    assert len(net["sha256"]) == 64
    md = (out / "tables.md").read_text()
    tex = (out / "tables.tex").read_text()
    worst = max(ifgsm["aee_adversarial"], snow["aee_adversarial"])
    for name, value in (("I-FGSM", ifgsm["aee_adversarial"]),
                        ("Snow (ours)", snow["aee_adversarial"])):
        text = f"{value:.2f}"
        shown = f"**{text}**" if value == worst else text
        assert f"| {name} | {shown} |" in md
        shown = r"\textbf{" + text + "}" if value == worst else text
        assert f"{name} & {shown} \\\\" in tex
    assert f"| snow | **{snow['aee_random']:.2f}** |" in md      # augmentations: one row
    for label in ("augmentations", "weatherattacks", "of_attacks"):
        assert r"\label{table:" + label + "}" in tex
    assert "of_attacks" in output


def test_rerun_resumes_without_redoing(bench, raft_small_weights):
    out, _ = bench
    before = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*.png")}
    again = invoke(grid_args(raft_small_weights, out, "--quiet"))
    assert again.exit_code == 0, again.output
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*.png")} == before


def test_bad_options_fail_before_writing(tmp_path):
    out = tmp_path / "b"
    result = invoke(["benchmark", "--presets", "hail", "--lp", "", "--out", out])
    assert result.exit_code == 2 and "hail" in result.output
    assert not out.exists()
    result = invoke(["benchmark", "--lp", "fgsm", "--presets", "", "--out", out])
    assert result.exit_code == 2 and "fgsm" in result.output
    result = invoke(["benchmark", "--checkpoint", "raft", "--out", out])
    assert result.exit_code == 2 and "NETWORK=FILE_OR_NAME" in result.output
    result = invoke(["benchmark", "--networks", "raft-small", "--amp", "--out", out])
    assert result.exit_code == 2 and "--amp needs a CUDA device" in result.output
    assert not out.exists()


@pytest.mark.parametrize("amp, expected", [(None, {"gma": True, "raft": False}),
                                           (False, {"gma": False, "raft": False})])
def test_amp_is_passed_on_to_every_run(demo_root, tmp_path, amp, expected):
    """Each run gets the request (default: each network's paper setting on CUDA) and records the
    resolved value in its manifest; nothing runs here, so no CUDA device is needed."""
    from weathergen.benchmark import BenchmarkSpec, run_grid
    from weathergen.datasets import open_dataset

    spec = BenchmarkSpec(dataset=open_dataset("demo", frames_per_scene=1), out=tmp_path,
                         networks=["gma", "raft"], presets=["snow"], lp_methods=["pcfa"],
                         device="cuda", amp=amp)
    jobs = []
    run_grid(spec, execute=jobs.append)
    assert [(j.model, j.amp) for j in jobs] == [(n, amp) for n in ("gma", "gma", "raft", "raft")]
    assert {j.model: j.config()["model"]["amp"] for j in jobs} == expected


def test_amp_for_a_network_without_the_mode_fails_before_any_run(demo_root, tmp_path):
    from weathergen.benchmark import BenchmarkSpec, run_grid
    from weathergen.datasets import open_dataset
    from weathergen.errors import ConfigError

    spec = BenchmarkSpec(dataset=open_dataset("demo", frames_per_scene=1), out=tmp_path,
                         networks=["gma", "spynet"], presets=["snow"], lp_methods=[],
                         device="cuda", amp=True)
    jobs = []
    with pytest.raises(ConfigError, match="'spynet' has no mixed-precision mode"):
        run_grid(spec, execute=jobs.append)
    assert jobs == []


def test_default_selection_is_five_pairs_per_scene(demo_root):
    from weathergen.benchmark import tr115_default
    from weathergen.datasets import open_dataset

    everything = open_dataset("demo")
    assert tr115_default(everything).selection.frames_per_scene == 5
    chosen = open_dataset("demo", frames_per_scene=1)
    assert tr115_default(chosen) is chosen
