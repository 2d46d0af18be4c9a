"""The Lp baselines PCFA (L2) and I-FGSM (L-infinity): their bounds and the box after every step,
the loss to the target decreasing on a real network, and `weathergen attack --method` end to end."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner

from weathergen.attack import (LpOptimisation, TargetSpec, l2_normalised,
                               l2_normalised_per_pair, lp_attack_batch, lp_settings,
                               random_perturbation)
from weathergen.errors import ConfigError


def lp_attack_pair(model, image1, image2, settings, target=TargetSpec("zero"), *, seed=0):
    """One pair's Lp attack: a batch of that pair alone."""
    return lp_attack_batch(model, image1, image2, settings, target, seeds=[seed])[0]


class ToyFlow(torch.nn.Module):
    """A small differentiable 'flow network': a fixed random conv of both frames."""

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.conv = torch.nn.Conv2d(6, 2, 3, padding=1)
        with torch.no_grad():
            self.conv.weight.copy_(torch.randn(self.conv.weight.shape, generator=g) * 5)
            self.conv.bias.fill_(3.0)

    def forward(self, a, b):
        return self.conv(torch.cat([a, b], 1))


def frames(seed=0, size=(12, 16)):
    g = torch.Generator().manual_seed(seed)
    x1 = torch.rand(1, 3, *size, generator=g)
    x1[..., :2, :] = 0.0        # pixels on both faces of the box
    x1[..., -2:, :] = 1.0
    return x1, torch.rand(1, 3, *size, generator=g)


def test_l2_normalised_is_the_rms_over_both_frames():
    d1, d2 = torch.full((1, 3, 2, 2), 0.3), torch.full((1, 3, 2, 2), -0.4)
    # 12 entries of 0.09 and 12 of 0.16: mean 0.125
    assert float(l2_normalised(d1, d2)) == pytest.approx(0.125 ** 0.5)


def test_pcfa_with_adam_respects_its_l2_bound_and_the_box_after_every_step():
    x1, x2 = frames()
    eps = 2e-3
    s = lp_settings("pcfa", epsilon=eps, steps=15, lr=0.05, optimizer="adam")   # the bound binds
    run = LpOptimisation(ToyFlow(), x1, x2, s)
    norms = []
    for _ in range(s.steps):
        _, _, loss, _, _ = run.evaluate()
        run.update(loss)
        y1, y2 = (f.detach() for f in run.frames())
        norms.append(float(l2_normalised(y1 - x1, y2 - x2)))
        for y in (y1, y2):
            assert float(y.min()) >= 0.0 and float(y.max()) <= 1.0
        assert norms[-1] <= eps * (1 + 1e-6)
    assert max(norms) > 0.99 * eps     # the projection was exercised, not just never needed


def test_ifgsm_respects_its_linf_bound_and_the_box_after_every_step():
    x1, x2 = frames(1)
    eps = 5e-3
    assert lp_settings("ifgsm", epsilon=eps, steps=6).lr == pytest.approx(eps / 6)  # default
    s = lp_settings("ifgsm", epsilon=eps, steps=6, lr=2.5 * eps / 6)    # the projection binds
    run = LpOptimisation(ToyFlow(), x1, x2, s)
    for _ in range(s.steps):
        _, _, loss, _, _ = run.evaluate()
        run.update(loss)
        for y, x in zip(run.frames(), (x1, x2)):
            y = y.detach()
            assert float((y - x).abs().max()) <= eps + 1e-7
            assert float(y.min()) >= 0.0 and float(y.max()) <= 1.0
    moved = (run.frames()[0].detach() - x1).abs()
    assert float(moved.max()) == pytest.approx(eps, rel=1e-4)   # interior pixels reach the bound
    assert float(moved[..., :2, :].max()) <= eps        # pixels at 0 cannot go below 0


def test_pcfa_penalty_is_the_reference_implementations():
    """μ · max(0, ‖δ‖² − ε²) with μ = 2500/ε, times 1.5 for a target other than zero flow."""
    x1, x2 = (torch.full((1, 3, 4, 4), 0.5),) * 2
    eps = 1e-2
    for target, mu in ((TargetSpec("zero"), 2500 / eps), (TargetSpec("negative"), 3750 / eps)):
        run = LpOptimisation(ToyFlow(), x1, x2, lp_settings("pcfa", epsilon=eps), target)
        assert run.mu == pytest.approx(mu)
        with torch.no_grad():      # every entry of both frames moved by 3ε: ‖δ‖ = 3ε
            for w in run.w:
                w.copy_(torch.atanh(2 * torch.full_like(w, 0.5 + 3 * eps) - 1))
        _, _, losses, distances, penalties = (t.detach() if torch.is_tensor(t) else t
                                              for t in run.evaluate())
        assert float(penalties[0]) == pytest.approx(mu * (9 - 1) * eps ** 2, rel=1e-3)
        assert float(losses[0]) == pytest.approx(float(distances[0] + penalties[0]))


def test_random_perturbation_has_the_budget():
    x1, x2 = (torch.full((1, 3, 8, 8), 0.5),) * 2
    r1, r2 = random_perturbation("pcfa", x1, x2, 5e-3, seed=3)
    assert float(l2_normalised(r1 - x1, r2 - x2)) == pytest.approx(5e-3, rel=1e-4)
    r1, r2 = random_perturbation("ifgsm", x1, x2, 5e-3, seed=3)
    assert torch.allclose((r1 - x1).abs(), torch.full_like(x1, 5e-3), atol=1e-7)
    again = random_perturbation("ifgsm", x1, x2, 5e-3, seed=3)
    assert torch.equal(again[0], r1)     # seeded


@pytest.mark.parametrize("method", ["pcfa", "ifgsm"])
def test_a_batch_equals_pairs_attacked_one_by_one(method):
    """Two pairs in one batch: each pair's steps, best step and frames as when attacked alone.
    PCFA's projection (with Adam) acts per pair: the second pair's pixels sit near the box faces,
    where tanh barely moves, so it stays inside the ball while the first is projected onto it."""
    saturated = tuple(torch.where(x > 0.5, 0.998, 0.002) for x in frames(3))
    pairs = [frames(2), saturated]
    eps = 2e-3
    # I-FGSM steps short of the bound: its distances keep falling, so the best step is no
    # rounding tie between equal steps on the bound
    lr = 0.02 if method == "pcfa" else eps / 6
    s = lp_settings(method, epsilon=eps, steps=5, lr=lr,
                    optimizer="adam" if method == "pcfa" else None)
    model = ToyFlow()
    seen = []
    batch = lp_attack_batch(model, torch.cat([p[0] for p in pairs]),
                            torch.cat([p[1] for p in pairs]), s, TargetSpec("negative"),
                            seeds=[7, 8], on_step=lambda i, r: seen.append((i, r.step)))
    assert seen == [(i, k) for k in range(6) for i in range(2)]
    norms = []
    for (x1, x2), seed, got in zip(pairs, (7, 8), batch):
        alone = lp_attack_pair(model, x1, x2, s, TargetSpec("negative"), seed=seed)
        assert got.best_step == alone.best_step
        assert [r.distance for r in got.history] == pytest.approx(
            [r.distance for r in alone.history], rel=1e-5)
        for a, b in zip(got.best_frames + got.random_frames, alone.best_frames + alone.random_frames):
            assert torch.allclose(a, b, atol=1e-6)
        assert torch.allclose(got.best_flow, alone.best_flow, atol=1e-4)
        d = [f - x for f, x in zip(got.best_frames, (x1, x2))]
        if method == "pcfa":
            norms.append(float(l2_normalised(*d)))
            assert norms[-1] <= eps * (1 + 1e-6)
        else:
            assert max(float(t.abs().max()) for t in d) <= eps + 1e-7
    if method == "pcfa":
        assert norms[0] > 0.99 * eps and 0 < norms[1] < 0.5 * eps


def test_l2_normalised_per_pair_is_each_pairs_norm():
    d1, d2 = torch.randn(3, 3, 4, 5), torch.randn(3, 3, 4, 5)
    per_pair = l2_normalised_per_pair(d1, d2)
    assert per_pair.shape == (3,)
    for i in range(3):
        assert float(per_pair[i]) == pytest.approx(float(l2_normalised(d1[i:i + 1], d2[i:i + 1])))


def test_settings_defaults_and_bad_values():
    assert lp_settings("pcfa").epsilon == 5e-3 and lp_settings("ifgsm").steps == 25
    # PCFA as published: L-BFGS with PyTorch's step size 1; Adam with its learning rate
    assert (lp_settings("pcfa").optimizer, lp_settings("pcfa").lr) == ("lbfgs", 1.0)
    assert lp_settings("pcfa", optimizer="adam").lr == 1e-3
    assert lp_settings("pcfa").to_dict()["optimizer"] == "lbfgs"
    assert "optimizer" not in lp_settings("ifgsm").to_dict()
    with pytest.raises(ConfigError, match="epsilon"):
        lp_settings("pcfa", epsilon=-1)
    with pytest.raises(ConfigError, match="method"):
        lp_settings("fgsm")
    with pytest.raises(ConfigError, match="lbfgs or adam"):
        lp_settings("pcfa", optimizer="sgd")
    with pytest.raises(ConfigError, match="applies to"):
        lp_settings("ifgsm", optimizer="adam")


class SmoothFlow(torch.nn.Module):
    """A small smooth 'flow network' (conv, tanh, conv): L-BFGS needs curvature, which the
    linear :class:`ToyFlow` lacks (its quasi-Newton steps leave the ball for good there)."""

    calls = 0

    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.a = torch.nn.Conv2d(6, 8, 3, padding=1)
        self.b = torch.nn.Conv2d(8, 2, 3, padding=1)
        with torch.no_grad():
            self.a.weight.copy_(torch.randn(self.a.weight.shape, generator=g) * 2)
            self.a.bias.zero_()
            self.b.weight.copy_(torch.randn(self.b.weight.shape, generator=g))
            self.b.bias.fill_(1.0)

    def forward(self, a, b):
        self.calls += 1
        return 3 * self.b(torch.tanh(self.a(torch.cat([a, b], 1))))


def test_lbfgs_pcfa_keeps_its_bound_and_reduces_the_loss():
    """PCFA as published on a tiny case: L-BFGS steps of several iterations each (one network
    pass each) with only the penalty holding the perturbation near the ball, so a step may leave
    it; the best step is the closest to the target among the steps within the bound."""
    x1, x2 = frames(5)
    eps = 5e-3
    s = lp_settings("pcfa", epsilon=eps, steps=6)
    model = SmoothFlow()
    assert isinstance(LpOptimisation(model, x1, x2, s).optimizer, torch.optim.LBFGS)
    model.calls = 0
    result = lp_attack_pair(model, x1, x2, s, TargetSpec("zero"), seed=1)
    # benign flow and random perturbation: 2 passes; then 7 measured steps and the L-BFGS
    # iterations after the first of each step
    assert model.calls > 2 + 7 + 6
    history = result.history
    assert any(r.penalty > 0 for r in history)              # a step outside the ball ...
    best = history[result.best_step]
    assert result.best_step > 0 and best.penalty == 0       # ... is never the best one
    assert best.distance == min(r.distance for r in history if r.penalty == 0)
    assert best.loss < 0.97 * history[0].loss               # the loss went down
    d = [f - x for f, x in zip(result.best_frames, (x1, x2))]
    assert 0.5 * eps < float(l2_normalised(*d)) <= eps
    for frame in result.best_frames:
        assert float(frame.min()) >= 0 and float(frame.max()) <= 1


def test_lbfgs_pcfa_attacks_the_pairs_of_a_batch_one_by_one():
    pairs = [frames(5), frames(6)]
    s = lp_settings("pcfa", epsilon=2e-3, steps=3)
    seen = []
    batch = lp_attack_batch(SmoothFlow(), torch.cat([p[0] for p in pairs]),
                            torch.cat([p[1] for p in pairs]), s, seeds=[1, 2],
                            on_step=lambda i, r: seen.append((i, r.step)))
    assert seen == [(0, k) for k in range(4)] + [(1, k) for k in range(4)]
    for (x1, x2), seed, got in zip(pairs, (1, 2), batch):
        alone = lp_attack_pair(SmoothFlow(), x1, x2, s, seed=seed)
        assert [r.distance for r in got.history] == [r.distance for r in alone.history]
        assert all(torch.equal(a, b) for a, b in zip(got.best_frames, alone.best_frames))


@pytest.mark.parametrize("method, optimizer", [("pcfa", "adam"), ("pcfa", "lbfgs"),
                                               ("ifgsm", None)])
def test_loss_to_target_decreases_with_raft_small(method, optimizer, raft_small_weights,
                                                  demo_root):
    from weathergen.datasets import open_dataset
    from weathergen.models import get_model

    torch.manual_seed(0)
    model = get_model("raft-small", str(raft_small_weights), iters=2)
    ds = open_dataset("demo", scenes=["courtyard"], frames_per_scene=1)
    pair = ds.load(ds.pairs()[0])
    small = [torch.nn.functional.interpolate(im[None], size=(48, 64), mode="bilinear",
                                             align_corners=False).clamp(0, 1)
             for im in (pair.image1, pair.image2)]
    eps = 2e-2 if method == "pcfa" else 5e-3
    lr = {"adam": 5e-3, "lbfgs": None, None: 1e-3}[optimizer]
    settings = lp_settings(method, epsilon=eps, steps=4, lr=lr, optimizer=optimizer)
    result = lp_attack_pair(model, *small, settings, TargetSpec("zero"), seed=0)
    distances = [r.distance for r in result.history]
    assert distances[0] > 0.1
    assert min(distances[1:]) < distances[0] * 0.98
    assert result.best_step > 0
    d = [b - s for b, s in zip(result.best_frames, small)]
    if method == "pcfa":
        assert float(l2_normalised(*d)) <= eps * (1 + 1e-6)
    else:
        assert max(float(t.abs().max()) for t in d) <= eps + 1e-7


# -- the command line ----------------------------------------------------------------------------

ONE_PAIR = ["--scenes", "courtyard", "--frames-per-scene", "1"]
PAIR = "courtyard_0001"


def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


@pytest.mark.slow
def test_cli_pcfa_writes_the_outputs_of_a_weather_attack(tmp_path, raft_small_weights):
    from weathergen.datasets import open_dataset
    from weathergen.io.exr import read_exr
    from weathergen.outputs import read_log

    out = tmp_path / "pcfa"
    args = ["attack", "--method", "pcfa", "--model", "raft-small", "--checkpoint",
            raft_small_weights, "--iters", "2", *ONE_PAIR, "--steps", "2", "--out", out]
    result = invoke(args)
    assert result.exit_code == 0, result.output
    assert "random perturbation" in result.output
    split = out / "training"
    assert sorted(p.name for p in (split / "pcfa_clean" / PAIR).glob("*.png")) == \
        ["frame_0001.png", "frame_0002.png"]
    for kind in ("benign", "initial", "adversarial", "target"):
        assert (split / "attack_flow" / PAIR / f"{kind}.flo").is_file()
    assert [r["step"] for r in read_log(split / "attack_log" / f"{PAIR}.csv")] == [0, 1, 2]
    summary = json.loads((out / "summary.json").read_text())
    manifest = json.loads((out / "manifest.json").read_text())
    pair_entry = next(iter(manifest["pairs"].values()))
    assert summary["pairs"] == 1
    for key in ("aee_random", "aee_adversarial", "target_initial", "target_adversarial"):
        assert summary[key] == pytest.approx(pair_entry[key])
    assert manifest["config"]["attack"]["method"] == "pcfa"
    assert manifest["config"]["attack"]["epsilon"] == 5e-3
    assert manifest["config"]["attack"]["optimizer"] == "lbfgs"       # as published
    # the float frames on disk keep the L2 bound against the clean frames and the box
    ds = open_dataset("demo", scenes=["courtyard"], frames_per_scene=1)
    pair = ds.load(ds.pairs()[0])
    exr = sorted((split / "pcfa_clean_exr" / PAIR).glob("*.exr"))
    adv = [torch.from_numpy(read_exr(p)["RGB"]).permute(2, 0, 1)[None] for p in exr]
    d = [a - c[None] for a, c in zip(adv, (pair.image1, pair.image2))]
    assert 0 < float(l2_normalised(*d)) <= 5e-3 * (1 + 1e-4)
    assert all(float(a.min()) >= 0 and float(a.max()) <= 1 for a in adv)
    # resuming skips the finished pair and keeps its figures
    again = invoke(args + ["--resume"])
    assert again.exit_code == 0, again.output
    assert json.loads((out / "summary.json").read_text()) == summary


@pytest.mark.slow
def test_cli_ifgsm_end_to_end(tmp_path, raft_small_weights):
    out = tmp_path / "ifgsm"
    result = invoke(["attack", "--method", "ifgsm", "--model", "raft-small", "--checkpoint",
                     raft_small_weights, "--iters", "2", *ONE_PAIR, "--steps", "2",
                     "--epsilon", "0.01", "--out", out, "--quiet"])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["target_adversarial"] < summary["target_initial"]
    # No weather covers any pixel: every pixel is "clear", and the summary has no mode.
    assert summary["weather_coverage"] == 0.0 and summary["aee_weather_px"] is None
    assert summary["aee_clear_px"] == pytest.approx(summary["aee_adversarial"], rel=1e-5)
    assert summary["fl_all"] is not None and summary["compat"] is None
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["attack"]["norm"] == "Linf"
    # inspect shows its metadata file (the pair, the attack's settings, no particles)
    meta = next((out / "training" / "particles").rglob("*.npz"))
    res = invoke(["inspect", meta])
    assert res.exit_code == 0, res.output
    assert "method ifgsm, epsilon 0.01, steps 2" in res.output, res.output
    assert "none (the attack perturbs the frames themselves)" in res.output


def test_cli_refuses_weather_options_with_an_lp_method(tmp_path):
    result = invoke(["attack", "--method", "pcfa", "--preset", "snow", "--out", tmp_path / "x"])
    assert result.exit_code == 2
    assert "--preset applies to weather attacks only" in result.output
    assert not (tmp_path / "x").exists()
    result = invoke(["attack", "--epsilon", "0.1", "--out", tmp_path / "y"])
    assert result.exit_code == 2 and "--epsilon" in result.output
    result = invoke(["attack", "--optimizer", "adam", "--out", tmp_path / "y"])
    assert result.exit_code == 2 and "--optimizer applies to --method pcfa only" in result.output
    result = invoke(["attack", "--method", "ifgsm", "--optimizer", "lbfgs", "--out", tmp_path / "y"])
    assert result.exit_code == 2 and "--optimizer applies to --method pcfa only" in result.output
    assert not (tmp_path / "y").exists()
