"""`attack --sequence`: one world weather for the pairs of a scene, optimised against all of them;
and the learning rate of each variable group, as used and as recorded."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from weathergen.attack import (FIELD_LR, AttackSettings, TargetSpec, attack_sequence, plan_attack,
                               scene_weather)
from weathergen.attack.pair import BatchOptimisation
from weathergen.engine import load_preset
from weathergen.errors import ConfigError
from weathergen.jobs import pair_particles, weather_seed

from .test_attack_pair import crop_pair

RATE = 24.0      # the demo scene's frame rate


@pytest.fixture(scope="module")
def street():
    """The three pairs of the demo street, cropped alike (one scene, frames 1-4)."""
    from weathergen.datasets import demo_pairs

    return [crop_pair(p, 40, 120, 96, 128).validate() for p in demo_pairs(scenes=["street"])]


@pytest.fixture(scope="module")
def raft_small(raft_small_weights):
    from weathergen.models import get_model

    return get_model("raft-small", checkpoint=raft_small_weights, iters=2)


def scene_records(pairs, preset, seed=1):
    records = [pair_particles(p, preset, seed, world_up="+z", frame_rate=RATE) for p in pairs]
    seeds = [weather_seed(preset, seed, p.id) for p in pairs]
    return records, scene_weather(pairs, records, preset, seeds, world_up="+z", frame_rate=RATE)


def world_points(record, frame2: bool) -> torch.Tensor:
    p = record.position.double() + record.offset1.double()
    return p + record.motion.double() + record.offset2.double() if frame2 else p


def test_one_weather_holds_in_every_pair_and_its_loss_falls(street, raft_small):
    preset = load_preset("snow-light", {"density": "400"})
    records, weather = scene_records(street, preset)
    assert all(r.count > 50 for r in records)
    settings = plan_attack(preset="snow-light", steps=2, sequence=True).settings
    assert "offset2" not in settings.optimize and settings.learning_rates == {
        g: FIELD_LR[g] for g in ("positions", "color", "transparency", "density", "airlight")}
    results = attack_sequence(raft_small, street, records, weather, settings, chunk=2)
    steps = [r.best_step for r in results]
    assert steps[0] > 0 and len(set(steps)) == 1                 # one best step for the scene
    mean = [sum(r.history[s].loss for r in results) / 3 for s in range(3)]
    assert min(mean[1:]) < mean[0], mean
    best = [r.best_particles for r in results]
    assert float(best[0].offset1.abs().max()) > 0 and float(best[0].offset2.abs().max()) == 0
    # frame 2 of a pair is frame 1 of the next: the same particles, moved alike, same looks
    for a, b in zip(best, best[1:]):
        d = torch.cdist(world_points(a, True), world_points(b, False))
        near, which = d.min(1)
        shared = near < 1e-5
        assert int(shared.sum()) > 0.8 * min(a.count, b.count)
        i, j = torch.nonzero(shared).flatten(), which[shared]
        assert torch.equal(a.offset1[i], b.offset1[j])
        assert torch.equal(a.color[i], b.color[j])
        assert torch.equal(a.transparency[i], b.transparency[j])
        moved = a.offset1[i].norm(dim=1) > 0
        assert bool(moved.any())                                 # and the attack moved them


def test_the_scene_shares_its_fog(street, raft_small):
    preset = load_preset("fog-heavy")
    records, weather = scene_records(street, preset)
    settings = AttackSettings(optimize=("density", "airlight"), steps=1, lr_defaults="field")
    results = attack_sequence(raft_small, street, records, weather, settings)
    airs = [r.best_particles.atmosphere for r in results]
    if results[0].best_step > 0:
        assert all(torch.equal(a.density, airs[0].density) for a in airs)
        assert all(torch.equal(a.airlight, airs[0].airlight) for a in airs)


def test_what_a_world_weather_cannot_be_is_refused(street, raft_small):
    preset = load_preset("snow-light")
    records, weather = scene_records(street[:1], preset)
    for settings, match in ((AttackSettings(optimize=("offset2",), steps=1), "offset2"),
                            (AttackSettings(optimize=("color",), steps=1, compat="reference"),
                             "reference")):
        with pytest.raises(ConfigError, match=match):
            attack_sequence(raft_small, street[:1], records, weather, settings)
    # pairs without a shared world (cameras known only relative to each other) have no scene
    unposed = [dataclasses.replace(p, cam1_from_world=None, cam2_from_world=None)
               for p in street[:2]]
    with pytest.raises(ConfigError, match="one world"):
        scene_records(unposed, preset)


def test_each_group_moves_at_its_own_rate_as_recorded(street, raft_small):
    plan = plan_attack(preset="rain-heavy+fog-light", overrides={"rain-heavy.density": "20"},
                       group_lr=["density=0.5"], steps=1)
    rates = plan.settings.learning_rates
    assert rates["density"] == 0.5 and rates["positions"] == FIELD_LR["positions"]
    records = [pair_particles(street[0], plan.preset, 1, world_up="+z", frame_rate=RATE)]
    run = BatchOptimisation(raft_small, street[:1], records, plan.settings, TargetSpec("zero"))
    used = {g["group"]: g["lr"] for g in run.optimizer.param_groups}
    assert used == rates
    assert plan.settings.to_dict()["learning_rates"] == used
    # the paper's presets keep the paper's one rate for their particles
    snow = plan_attack(preset="snow").settings
    assert snow.learning_rates == {"positions": 1e-5, "color": 1e-5, "transparency": 1e-5}
    assert plan_attack(preset="snow", lr=0.1).settings.learning_rates["color"] == 0.1
    with pytest.raises(ConfigError, match="group_lr"):
        plan_attack(preset="fog-heavy", group_lr=["fog=1"])


# -- the command, end to end ---------------------------------------------------------------------

def invoke(args):
    from click.testing import CliRunner

    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def test_a_paper_preset_is_refused_in_one_line(tmp_path):
    result = invoke(["attack", "--model", "raft-small", "--preset", "snow", "--sequence",
                     "--steps", "1", "--out", tmp_path / "out"])
    assert result.exit_code == 2
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "--sequence" in lines[0] and "paper preset" in lines[0]
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_the_command_writes_both_figures_and_its_output_rerenders(tmp_path, raft_small_weights,
                                                                  monkeypatch):
    import weathergen.attack.pair as pair_module
    import weathergen.attack.sequence as sequence_module

    used = []
    original = pair_module.group_optimizer

    def spy(variables, settings):
        optimizer = original(variables, settings)
        used.append({g["group"]: g["lr"] for g in optimizer.param_groups})
        return optimizer

    monkeypatch.setattr(pair_module, "group_optimizer", spy)
    monkeypatch.setattr(sequence_module, "group_optimizer", spy)
    out = tmp_path / "seq"
    result = invoke(["attack", "--model", "raft-small", "--checkpoint", raft_small_weights,
                     "--iters", "2", "--scenes", "street", "--frames-per-scene", "2",
                     "--preset", "snow-light", "--set", "density=100", "--sequence",
                     "--steps", "2", "--seed", "1", "--group-lr", "color=0.1", "--out", out])
    assert result.exit_code == 0, result.output
    assert "(the pair attacked alone: " in result.output and "per scene" in result.output
    summary = json.loads((out / "summary.json").read_text())
    scene = summary["scenes"]["demo/training/street"]
    assert scene["pairs"] == 2 and scene["per_pair_aee_adversarial"] is not None
    assert summary["per_pair_aee_adversarial"] == pytest.approx(scene["per_pair_aee_adversarial"])
    manifest = json.loads((out / "manifest.json").read_text())
    rates = manifest["config"]["attack"]["learning_rates"]
    assert rates["color"] == 0.1 and manifest["config"]["attack"]["sequence"] is True
    assert used and all(u == rates for u in used)         # the sequence's and the pairs' alone
    again = tmp_path / "again"
    result = invoke(["render", "--particles", out, "--scenes", "street", "--frames-per-scene",
                     "2", "--out", again, "--quiet"])
    assert result.exit_code == 0, result.output
    import cv2

    written = sorted((out / "training" / "snow-light_adv_clean").glob("*/*.png"))
    assert len(written) == 4
    for path in written:
        rendered = again / "training" / "snow-light_clean" / path.parent.name / path.name
        assert np.array_equal(cv2.imread(str(path)), cv2.imread(str(rendered))), path
    # a scene with an unfinished pair is redone whole on --resume; a finished one is skipped
    (out / "training" / "particles" / "street_0002" / "frame_0002.npz").unlink()
    args = ["attack", "--model", "raft-small", "--checkpoint", raft_small_weights, "--iters", "2",
            "--scenes", "street", "--frames-per-scene", "2", "--preset", "snow-light", "--set",
            "density=100", "--sequence", "--steps", "2", "--seed", "1", "--group-lr", "color=0.1",
            "--out", out, "--resume"]
    for _ in range(2):
        assert invoke(args).exit_code == 0
    runs = json.loads((out / "manifest.json").read_text())["runs"]
    assert [(r["written"], r["skipped"]) for r in runs] == [(2, 0), (2, 0), (0, 2)]


@pytest.mark.slow
def test_stereo_attacks_both_cameras_and_rerenders_as_render_stereo(tmp_path, raft_small_weights):
    import shutil

    from fake_datasets import demo_sequence, write_fake_spring

    from weathergen.attack import second_frames, second_view
    from weathergen.datasets import open_dataset, right_camera
    from weathergen.engine import load_particles
    from weathergen.io.images import read_image

    frames, _ = demo_sequence("street")
    root = write_fake_spring(tmp_path / "spring", frames[:3])
    scene = root / "train" / "0001"
    (scene / "frame_right").mkdir()
    for n in (1, 2, 3):        # the right camera's frames (their content does not matter here)
        shutil.copy(scene / "frame_left" / f"frame_left_{n:04d}.png",
                    scene / "frame_right" / f"frame_right_{n:04d}.png")
    data = ["--dataset", "spring", "--root", root, "--split", "train"]
    out = tmp_path / "out"
    result = invoke(["attack", *data, "--model", "raft-small", "--checkpoint", raft_small_weights,
                     "--iters", "2", "--preset", "snow-moderate", "--set", "far=5",
                     "--sequence", "--stereo", "--steps", "2", "--out", out])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["second_aee_random"] > 0 and summary["second_aee_adversarial"] is not None
    assert summary["scenes"]["spring/train/0001"]["second_aee_random"] is not None
    # the second camera the attack saw is the one `render --stereo` draws from the stored weather
    again = tmp_path / "again"
    result = invoke(["render", *data, "--particles", out, "--stereo", "--out", again, "--quiet"])
    assert result.exit_code == 0, result.output
    dataset = open_dataset("spring", root, split="train")
    ref = dataset.pairs()[0]
    pair = dataset.load(ref)
    record = load_particles(out / "training" / "particles" / "0001_0001" / "frame_0001.npz")
    with torch.no_grad():
        drawn = second_frames(record, second_view(pair, right_camera(dataset, pair)), 250.0)
    for t, frame in enumerate(drawn):
        written = read_image(again / "training" / "snow-moderate_clean_right" / "0001_0001"
                             / f"frame_{t + 1:04d}.png")
        assert np.abs(frame.permute(1, 2, 0).numpy() - written).max() <= 0.5 / 255 + 1e-6
    result = invoke(["attack", "--preset", "snow-moderate", "--stereo", "--out", tmp_path / "x"])
    assert result.exit_code == 2 and "--stereo applies to --sequence" in result.output
