"""`weathergen evaluate`: robustness AEE(f, f̌) and EPE against ground truth for a render output."""

from __future__ import annotations

import json

import pytest
import torch
from click.testing import CliRunner

ONE_PAIR = ["--scenes", "street", "--frames-per-scene", "1"]


def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def model(raft_small_weights):
    from weathergen.models import get_model

    return get_model("raft-small", checkpoint=raft_small_weights, iters=2)


def evaluate_frames(model, clean1, clean2, weather1, weather2, gt=None, valid=None):
    """``(AEE(f, f̌), EPE(f, gt), EPE(f̌, gt))`` for one pair of (3, H, W) frames, as evaluate
    measures them."""
    from weathergen.attack.evaluate import _figures, frame_flows

    return _figures(*frame_flows(model, clean1, clean2, weather1, weather2, "cpu"), gt, valid)


def test_identical_frames_have_zero_robustness_error(model):
    from weathergen.datasets import demo_pairs
    from weathergen.flow import aee

    pair = demo_pairs(scenes=["street"], frames_per_scene=1)[0]
    a, e_clean, e_weather = evaluate_frames(model, pair.image1, pair.image2, pair.image1,
                                            pair.image2, pair.flow, pair.flow_valid)
    assert a == pytest.approx(0.0, abs=1e-4)
    assert e_clean == pytest.approx(e_weather, abs=1e-4)
    with torch.no_grad():
        flow = model(pair.image1[None], pair.image2[None])
    assert e_clean == pytest.approx(float(aee(flow, pair.flow[None], pair.flow_valid[None])[0]),
                                    rel=1e-4)
    # Swapping the frames for others changes the flow: the measure is not blind.
    a, _, _ = evaluate_frames(model, pair.image1, pair.image2, pair.image2, pair.image1)
    assert a > 0.5


@pytest.fixture(scope="module")
def weather(tmp_path_factory):
    out = tmp_path_factory.mktemp("evaluate") / "snow"
    rendered = invoke(["render", "--preset", "snow", "--set", "count=800", *ONE_PAIR,
                       "--out", out])
    assert rendered.exit_code == 0, rendered.output
    return out


@pytest.mark.slow
def test_evaluate_a_render_output_from_the_cli(model, weather, tmp_path, raft_small_weights):
    result = invoke(["evaluate", "--weather", weather, "--model", "raft-small", "--checkpoint",
                     raft_small_weights, "--iters", "2", "--json", tmp_path / "eval.json"])
    assert result.exit_code == 0, result.output
    assert "AEE(f, f̌)" in result.output and "EPE weather" in result.output
    data = json.loads((tmp_path / "eval.json").read_text())
    (row,) = data["pairs"]
    assert row["pair"] == "demo/training/street/0001"
    assert row["aee_weather"] > 0.0             # 800 snowflakes change the flow
    assert row["epe_clean"] is not None and row["epe_weather"] is not None
    assert data["summary"]["aee_weather"] == pytest.approx(row["aee_weather"])
    # Figures by region: the weather's pixels and the rest make up the whole AEE; rates from
    # the demo's ground truth.
    share = row["weather_coverage"] / 100
    assert 0 < share < 1
    assert (share * row["aee_weather_px"] + (1 - share) * row["aee_clear_px"]
            == pytest.approx(row["aee_weather"], rel=1e-4))
    assert row["aee_weather_px"] > row["aee_clear_px"]      # the flakes disturb their own pixels most
    for key in ("epe_weather_px", "epe_clear_px", "fl_all", "outliers_1px", "outliers_3px",
                "outliers_5px"):
        assert row[key] is not None and data["summary"][key] == pytest.approx(row[key]), key
    assert "Fl-all" in result.output

    # Cross-check against the flow computed here on the frames the render wrote.
    from weathergen.datasets import demo_pairs
    from weathergen.flow import aee
    from weathergen.io.images import read_image

    pair = demo_pairs(scenes=["street"], frames_per_scene=1)[0]
    frames = [torch.from_numpy(read_image(weather / "training" / "snow_clean" / "street_0001" /
                                          f"frame_{i:04d}.png")).permute(2, 0, 1)[None]
              for i in (1, 2)]
    with torch.no_grad():
        clean = model(pair.image1[None], pair.image2[None])
        snowy = model(frames[0], frames[1])
    assert row["aee_weather"] == pytest.approx(float(aee(snowy, clean)[0]), rel=1e-3)


def test_evaluate_refuses_a_folder_without_manifest(tmp_path):
    result = invoke(["evaluate", "--weather", tmp_path, "--model", "raft-small"])
    assert result.exit_code == 2 and "manifest.json" in result.output


def test_evaluate_refuses_a_folder_without_pairs(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"outputs": {"pass": "x"},
                                                        "input": {"dataset": "demo"}}))
    result = invoke(["evaluate", "--weather", tmp_path, "--model", "raft-small"])
    assert result.exit_code == 2 and "no complete weather pairs" in result.output


def test_evaluate_unknown_model_lists_the_known_ones(weather):
    result = invoke(["evaluate", "--weather", weather, "--model", "gma9"])
    assert result.exit_code == 2
    assert "gma9" in result.output and "raft-small" in result.output
