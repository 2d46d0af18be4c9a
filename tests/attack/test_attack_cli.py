"""`weathergen attack` end to end on the demo scene with tiny settings, its outputs, re-rendering
them through `weathergen render --particles`, resuming, and its error paths."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

ONE_PAIR = ["--scenes", "courtyard", "--frames-per-scene", "1"]

#: Every test here runs whole commands on the demo scene.
pytestmark = pytest.mark.slow


def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def tiny_attack(weights, out, *extra):
    return ["attack", "--model", "raft-small", "--checkpoint", weights, "--iters", "2",
            *ONE_PAIR, "--steps", "2", "--set", "count=150", "--seed", "1", "--out", out, *extra]


@pytest.fixture(scope="module")
def attack_out(tmp_path_factory, raft_small_weights):
    out = tmp_path_factory.mktemp("attack") / "snow"
    result = invoke(tiny_attack(raft_small_weights, out))
    assert result.exit_code == 0, result.output
    return out, result.output


PAIR = "courtyard_0001"


def test_attack_writes_every_output(attack_out):
    out, output = attack_out
    assert "AEE(f, f̌)" in output and "EPE vs ground truth" in output
    split = out / "training"
    frames = sorted((split / "snow_adv_clean" / PAIR).glob("*.png"))
    assert [f.name for f in frames] == ["frame_0001.png", "frame_0002.png"]
    for kind in ("benign", "initial", "adversarial", "target"):
        assert (split / "attack_flow" / PAIR / f"{kind}.flo").is_file()
        assert (split / "attack_flow" / PAIR / f"{kind}.png").is_file()
    assert (split / "particles" / PAIR / "frame_0001.npz").is_file()

    from weathergen.io.sintel_formats import read_flo

    benign = read_flo(split / "attack_flow" / PAIR / "benign.flo")
    assert benign.shape == (176, 384, 2) and np.abs(benign).max() > 0.5   # a real flow field
    target = read_flo(split / "attack_flow" / PAIR / "target.flo")
    assert np.all(target == 0)                                              # default: zero flow


def test_flow_pictures_share_one_scale(attack_out):
    import torch

    from weathergen.flow import flow_to_color
    from weathergen.io.images import read_raw
    from weathergen.io.sintel_formats import read_flo

    out, _ = attack_out
    folder = out / "training" / "attack_flow" / PAIR
    kinds = ("benign", "initial", "adversarial", "target")
    flows = [torch.from_numpy(read_flo(folder / f"{k}.flo").transpose(2, 0, 1).copy())
             for k in kinds]
    shared = flow_to_color(flows)
    alone = flow_to_color(flows[0])
    for kind, expected in zip(kinds, shared):
        written = read_raw(folder / f"{kind}.png")[..., ::-1]     # stored as BGR
        assert np.array_equal(written, expected.permute(1, 2, 0).numpy()), kind
    # The benign flow is not the longest of the comparison, so its own scale would differ.
    assert not torch.equal(alone, shared[0])


def test_attack_log_and_summary(attack_out):
    out, output = attack_out
    assert "research code's figure" not in output and "(vs the random" not in output
    from weathergen.outputs import read_log

    rows = read_log(out / "training" / "attack_log" / f"{PAIR}.csv")
    assert [r["step"] for r in rows] == [0, 1, 2]
    best = [r["best_distance"] for r in rows]
    assert all(b <= a for a, b in zip(best, best[1:]))
    for r in rows:   # the loss is the distance to the target plus the offset penalty
        assert r["loss"] == pytest.approx(r["distance"] + r["penalty"], rel=1e-5)
    assert best[-1] == pytest.approx(min(r["distance"] for r in rows), rel=1e-5)

    summary = json.loads((out / "summary.json").read_text())
    assert summary["pairs"] == 1
    for key in ("aee_random", "aee_adversarial", "target_initial", "target_adversarial",
                "epe_benign", "epe_random", "epe_adversarial"):
        assert summary[key] is not None and summary[key] >= 0, key
    # The start of the log is the random weather the summary reports.
    assert summary["aee_random"] == pytest.approx(rows[0]["robustness"], rel=1e-4)
    assert summary["target_initial"] == pytest.approx(rows[0]["distance"], rel=1e-4)

    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["format"] == "weathergen-attack"
    assert manifest["preset_name"] == "snow" and manifest["preset"]["count"] == 150
    attack = manifest["config"]["attack"]
    assert attack["optimize"] == ["offset1", "offset2", "color", "transparency"]
    assert attack["learning_rates"] == {"positions": 1e-5, "color": 1e-5, "transparency": 1e-5}
    assert attack["alpha1"] == attack["alpha2"] == 1000.0
    assert attack["compat"] == summary["compat"] == "paper"          # the default
    # Figures by region: the two regions split the pixels, so their AEEs, weighted by the
    # weather's coverage, make up AEE(f, f̌) (one pair); the demo scene has ground truth.
    share = summary["weather_coverage"] / 100
    assert 0 < share < 1
    assert (share * summary["aee_weather_px"] + (1 - share) * summary["aee_clear_px"]
            == pytest.approx(summary["aee_adversarial"], rel=1e-4))
    for key in ("epe_weather_px", "epe_clear_px", "fl_all", "outliers_1px", "outliers_3px",
                "outliers_5px"):
        assert summary[key] is not None and summary[key] >= 0, key
    assert summary["outliers_1px"] >= summary["outliers_3px"] >= summary["outliers_5px"]
    assert attack["transparency_max"] == 1.0
    (entry,) = manifest["pairs"].values()
    assert entry["status"] == "written" and entry["steps"] == 2
    # Mixed precision: RAFT-small's paper setting is off, and on the CPU it is off anyway.
    assert manifest["config"]["model"]["amp"] is False and summary["amp"] is False
    # the explicit count is used on the demo frame as given, and recorded with its rule
    assert entry["particles"] == 150 and manifest["preset"]["scale_count"] is False
    from weathergen.outputs import read_metadata, stored_frame_scaling

    (npz,) = (out / "training" / "particles").rglob("*.npz")
    recorded = stored_frame_scaling(read_metadata(npz))
    assert (recorded["count"], recorded["count_rule"], recorded["width"]) == (150, "fixed", 384)


def test_attack_output_rerenders_through_render_particles(attack_out, tmp_path):
    out, _ = attack_out
    again = tmp_path / "rerender"
    result = invoke(["render", "--particles", out, *ONE_PAIR, "--out", again])
    assert result.exit_code == 0, result.output
    from weathergen.io.images import read_image

    for name in ("frame_0001.png", "frame_0002.png"):
        attacked = read_image(out / "training" / "snow_adv_clean" / PAIR / name)
        rendered = read_image(again / "training" / "snow_clean" / PAIR / name)
        # Same stored particles, same renderer: equal up to float summation order.
        assert np.abs(attacked - rendered).max() <= 1.5 / 255


def test_evaluate_on_the_attack_output_reproduces_its_figures(attack_out, tmp_path, raft_small_weights):
    out, _ = attack_out
    result = invoke(["evaluate", "--weather", out, "--model", "raft-small", "--checkpoint",
                     raft_small_weights, "--iters", "2", "--json", tmp_path / "eval.json"])
    assert result.exit_code == 0, result.output
    (row,) = json.loads((tmp_path / "eval.json").read_text())["pairs"]
    summary = json.loads((out / "summary.json").read_text())
    # Both measure the written 8-bit frames with the same network.
    assert row["aee_weather"] == pytest.approx(summary["aee_adversarial"], rel=1e-4, abs=1e-5)
    assert row["epe_weather"] == pytest.approx(summary["epe_adversarial"], rel=1e-4, abs=1e-5)
    assert row["epe_clean"] == pytest.approx(summary["epe_benign"], rel=1e-4, abs=1e-5)
    assert json.loads((tmp_path / "eval.json").read_text())["amp"] is False


@pytest.mark.parametrize("command", ["attack", "evaluate"])
def test_mixed_precision_on_the_cpu_is_refused_before_anything_is_written(command, tmp_path,
                                                                          raft_small_weights):
    from weathergen.cli.main import _register, cli

    _register()
    place = (["--out", tmp_path / "x", *ONE_PAIR] if command == "attack"
             else ["--weather", tmp_path / "x", "--json", tmp_path / "x.json"])
    result = CliRunner().invoke(cli, [str(a) for a in [
        command, "--model", "raft-small", "--checkpoint", raft_small_weights, "--amp", *place]])
    assert result.exit_code == 2
    (line,) = result.output.strip().splitlines()
    assert line.startswith("Error: --amp needs a CUDA device")
    assert not (tmp_path / "x").exists() and not (tmp_path / "x.json").exists()
    # --no-amp is what the CPU does anyway
    if command == "attack":
        ok = invoke(tiny_attack(raft_small_weights, tmp_path / "y", "--no-amp", "--steps", "1",
                                "--quiet"))
        assert ok.exit_code == 0, ok.output
        assert json.loads((tmp_path / "y" / "summary.json").read_text())["amp"] is False


def test_resume_skips_finished_pairs_and_plain_rerun_refuses(attack_out, raft_small_weights):
    out, _ = attack_out
    log = out / "training" / "attack_log" / f"{PAIR}.csv"
    before = log.stat().st_mtime_ns
    refused = invoke(tiny_attack(raft_small_weights, out))
    assert refused.exit_code == 2 and "--resume" in refused.output
    resumed = invoke(tiny_attack(raft_small_weights, out, "--resume"))
    assert resumed.exit_code == 0, resumed.output
    assert "skipped" in resumed.output
    assert log.stat().st_mtime_ns == before
    other = invoke(tiny_attack(raft_small_weights, out, "--resume", "--steps", "5"))
    assert other.exit_code == 2 and "different settings" in other.output


def test_fog_configuration_freezes_the_second_offset(tmp_path, raft_small_weights):
    out = tmp_path / "fog"
    result = invoke(["attack", "--config", "fog", "--model", "raft-small", "--checkpoint",
                     raft_small_weights, "--iters", "2", *ONE_PAIR, "--steps", "1", "--set", "count=2",
                     "--out", out, "--target", "1.5,-2"])
    assert result.exit_code == 0, result.output
    config = json.loads((out / "manifest.json").read_text())["config"]
    assert config["preset_name"] == "fog"
    assert config["attack"]["optimize"] == ["offset1", "color", "transparency"]
    assert config["attack"]["beta"] == 30.0
    assert config["attack"]["target"] == "constant 1.5,-2"


def test_stored_fog_particles_keep_the_second_offset_fixed(tmp_path, raft_small_weights):
    fog = tmp_path / "fog"
    rendered = invoke(["render", "--preset", "fog", "--set", "count=2", *ONE_PAIR, "--out", fog])
    assert rendered.exit_code == 0, rendered.output
    out = tmp_path / "attack"
    result = invoke(["attack", "--particles", fog, "--model", "raft-small", "--checkpoint",
                     raft_small_weights, "--iters", "1", *ONE_PAIR, "--steps", "1", "--out", out])
    assert result.exit_code == 0, result.output
    config = json.loads((out / "manifest.json").read_text())["config"]
    assert config["preset_name"] == "fog"
    assert config["attack"]["optimize"] == ["offset1", "color", "transparency"]
    assert config["attack"]["beta"] == 30.0
    refused = invoke(["attack", "--particles", fog, "--preset", "snow", "--model", "raft-small",
                      "--checkpoint", raft_small_weights, *ONE_PAIR, "--out", tmp_path / "x"])
    assert refused.exit_code == 2 and "'fog'" in refused.output
    assert not (tmp_path / "x").exists()


def test_interrupted_run_resumes_at_the_unfinished_pair(tmp_path, monkeypatch, raft_small_weights):
    import weathergen.attack.job as attack_job

    real = attack_job.attack_batch

    def interrupted(model, pairs, *args, **kwargs):
        if pairs[0].id.scene == "street":    # the second pair: Ctrl-C in its first step
            raise KeyboardInterrupt
        return real(model, pairs, *args, **kwargs)

    out = tmp_path / "two"
    args = ["attack", "--model", "raft-small", "--checkpoint", raft_small_weights, "--iters", "1",
            "--scenes", "courtyard,street", "--frames-per-scene", "1", "--steps", "1",
            "--set", "count=40", "--out", out]
    monkeypatch.setattr(attack_job, "attack_batch", interrupted)
    stopped = invoke(args)
    assert stopped.exit_code == 130 and "--resume" in stopped.output
    manifest = json.loads((out / "manifest.json").read_text())
    assert [e["pair"] for e in manifest["pairs"].values()] == ["demo/training/courtyard/0001"]
    assert not (out / "training" / "particles" / "street_0001").exists()
    first_log = out / "training" / "attack_log" / "courtyard_0001.csv"
    before = first_log.stat().st_mtime_ns

    monkeypatch.setattr(attack_job, "attack_batch", real)
    resumed = invoke([*args, "--resume"])
    assert resumed.exit_code == 0, resumed.output
    assert first_log.stat().st_mtime_ns == before          # the finished pair was not redone
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(e["pair"] for e in manifest["pairs"].values()) == [
        "demo/training/courtyard/0001", "demo/training/street/0001"]
    assert [(r["written"], r["skipped"]) for r in manifest["runs"]] == [(1, 0), (1, 1)]
    assert manifest["summary"]["pairs"] == 2


# -- error paths ----------------------------------------------------------------------------------

def test_a_folder_another_run_is_writing_is_refused(attack_out, raft_small_weights):
    """One attack run at a time writes a folder: a second one (here: its lock held by this test,
    as a running attack holds it) stops with one line naming the holder, and touches nothing."""
    from weathergen.attack.job import ATTACK_LOCK
    from weathergen.io.lock import FolderLock

    out, _ = attack_out
    manifest = (out / "manifest.json").read_bytes()
    with FolderLock(out / ATTACK_LOCK, str(out)):
        busy = invoke(tiny_attack(raft_small_weights, out, "--resume"))
    assert busy.exit_code == 2, busy.output
    assert "being written by another weathergen run" in busy.output
    assert len(busy.output.strip().splitlines()) == 1 and "Traceback" not in busy.output
    assert (out / "manifest.json").read_bytes() == manifest
    # the finished run released it: a resumed run may go on
    assert invoke(tiny_attack(raft_small_weights, out, "--resume")).exit_code == 0


def test_a_finished_attack_leaves_no_lock_file(attack_out):
    out, _ = attack_out
    assert (out / "manifest.json").is_file() and not list(out.rglob(".weathergen-lock*"))


def test_unknown_model_lists_the_known_ones(tmp_path):
    result = invoke(["attack", "--model", "flownet9", *ONE_PAIR, "--out", tmp_path / "x"])
    assert result.exit_code == 2
    assert "flownet9" in result.output and "raft-small" in result.output
    assert not (tmp_path / "x").exists()


def test_bad_optimize_value_names_the_choices(tmp_path):
    result = invoke(["attack", "--optimize", "offset1,size", *ONE_PAIR, "--out", tmp_path / "x"])
    assert result.exit_code == 2
    assert "'size'" in result.output and "offset1, offset2, color, transparency" in result.output


def test_missing_checkpoint_says_which_file_goes_where(tmp_path):
    # The test session's cache is empty: RAFT's default checkpoint is not there.
    result = invoke(["attack", "--model", "raft", *ONE_PAIR, "--out", tmp_path / "x"])
    assert result.exit_code == 2
    assert "raft-sintel.pth" in result.output and "put" in result.output
    assert not (tmp_path / "x").exists()


def test_checkpoint_path_that_does_not_exist(tmp_path):
    result = invoke(["attack", "--model", "raft-small", "--checkpoint", tmp_path / "nope.pth",
                     *ONE_PAIR, "--out", tmp_path / "x"])
    assert result.exit_code == 2 and "nope.pth" in result.output


def test_unknown_configuration_and_target(tmp_path):
    result = invoke(["attack", "--config", "hail", "--out", tmp_path / "x"])
    assert result.exit_code == 2 and "grey-offset1" in result.output
    result = invoke(["attack", "--target", "sideways", "--out", tmp_path / "x"])
    assert result.exit_code == 2 and "--target" in result.output


def test_missing_target_file(tmp_path, raft_small_weights):
    result = invoke(["attack", "--model", "raft-small", "--checkpoint", raft_small_weights, *ONE_PAIR,
                     "--target", tmp_path / "goal.flo", "--out", tmp_path / "x"])
    assert result.exit_code == 2 and "goal.flo" in result.output


def test_compat_reference_is_recorded_in_manifest_and_summary(tmp_path, raft_small_weights):
    out = tmp_path / "reference"
    result = invoke(tiny_attack(raft_small_weights, out, "--compat", "reference"))
    assert result.exit_code == 0, result.output
    assert "compat reference" in result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["compat"] == "reference" and summary["aee_adversarial"] >= 0
    # The printed adversarial AEE is the research code's figure, and says so.
    words = " ".join(result.output.split())
    assert (f"adversarial (vs the random weather's flow) {summary['aee_adversarial']:.3f}"
            in words)
    assert f"{summary['aee_adversarial']:.3f} *" in words
    assert ("* --compat reference: the research code's figure, the best step's flow against the "
            "random weather's flow" in words)
    attack = json.loads((out / "manifest.json").read_text())["config"]["attack"]
    assert attack["compat"] == "reference" and attack["transparency_max"] == 0.75   # snow
    # Resuming under the other mode is refused: the settings differ.
    again = invoke(tiny_attack(raft_small_weights, out, "--resume"))
    assert again.exit_code == 2 and "different settings" in again.output


def test_compat_reference_is_refused_for_lp_attacks(tmp_path):
    result = invoke(["attack", "--method", "ifgsm", "--compat", "reference", *ONE_PAIR,
                     "--out", tmp_path / "x"])
    assert result.exit_code == 2 and "--compat" in result.output and "weather" in result.output
    assert not (tmp_path / "x").exists()


def test_strong_forward_motion_is_recorded_and_noted_once_by_the_attack(tmp_path, raft_small_weights):
    """The attack samples a paper preset's particles as render does, and says the same of pairs
    whose frame 2 keeps fewer than half of the particles frame 1 shows: marked ``few_in_frame2``
    beside ``visible`` in the manifest, one note for the run; a still camera is not marked."""
    from engine_scenes import assert_few_in_frame2_marked, write_motion_scenes

    small = dict(size=(64, 96), focal=80.0, wall_columns=30)
    root = tmp_path / "sintel"
    write_motion_scenes(root, **small)
    out = tmp_path / "out"
    res = invoke(["attack", "--root", root, "--model", "raft-small", "--checkpoint",
                  raft_small_weights, "--iters", "1", "--steps", "1", "--set", "count=300",
                  "--set", "scale_count=false", "--out", out, "-q"])
    assert res.exit_code == 0, res.output
    notes = [line for line in res.output.splitlines() if "frame 2 shows" in line]
    assert len(notes) == 1, res.output
    assert notes[0].startswith("Note: in 2 pairs") and "snow-moderate" in notes[0]
    assert_few_in_frame2_marked(out)
    pairs = json.loads((out / "manifest.json").read_text())["pairs"]
    # a resumed run keeps the marks and says nothing again (it sampled nothing)
    res = invoke(["attack", "--root", root, "--model", "raft-small", "--checkpoint",
                  raft_small_weights, "--iters", "1", "--steps", "1", "--set", "count=300",
                  "--set", "scale_count=false", "--out", out, "-q", "--resume"])
    assert res.exit_code == 0 and "frame 2 shows" not in res.output, res.output
    again = json.loads((out / "manifest.json").read_text())["pairs"]
    assert {k: (e["visible"], e["few_in_frame2"]) for k, e in again.items()} == \
        {k: (e["visible"], e["few_in_frame2"]) for k, e in pairs.items()}
