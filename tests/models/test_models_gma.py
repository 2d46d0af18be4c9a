"""GMA behind the model contract: the released key layout, strict loading, the global motion
aggregation against a naive computation, shapes, gradients, named checkpoints and the CLI."""

from __future__ import annotations

import io

import pytest
import torch
from model_checks import (assert_flow_at_input_size, assert_gradient_reaches_both_images,
                          assert_loads_strictly, attack_then_evaluate, input_gradient,
                          load_error, random_frames, random_release, saved, serve,
                          tiny_sintel)
from numerics import assert_float32_close, rounding_k

from weathergen.errors import ConfigError, FormatError
from weathergen.models import build_model, get_model
from weathergen.models.gma import ContextAttention, MotionAggregator
from model_layouts import gma_attention_layout, gma_update_layout, raft_encoder_layout


# -- the released key layout ------------------------------------------------------------------

GMA_LAYOUT = {**raft_encoder_layout("fnet.", 256, "instance"),
              **raft_encoder_layout("cnet.", 256, "batch"),
              **gma_update_layout("update_block.", 4 * 81),
              **gma_attention_layout("att.")}


def test_state_dict_has_the_released_names_and_shapes():
    state = build_model("gma").network.state_dict()
    assert {k: tuple(v.shape) for k, v in state.items()} == GMA_LAYOUT
    assert state["att.pos_emb.rel_ind"].dtype == torch.int64
    params = sum(p.numel() for p in build_model("gma").parameters())
    assert params == 5_879_873  # GMA's published size, "5.9M"


# -- strict loading ------------------------------------------------------------------------------

@pytest.mark.parametrize("prefix", ["module.", ""])
def test_a_saved_random_model_loads_strictly(prefix, tmp_path):
    state, source = random_release("gma", prefix)
    path = saved(state, tmp_path / "gma.pth")
    assert_loads_strictly("gma", path, state, source, prefix, (64, 72))


def test_a_perturbed_file_fails_listing_what_does_not_match(tmp_path):
    state, _ = random_release("gma")
    del state["module.update_block.aggregator.gamma"]
    state["module.update_block.aggregator.project.weight"] = torch.zeros(128, 128, 1, 1)
    state["module.att.to_qk.weight"] = torch.zeros(512, 128, 1, 1)  # two heads
    message = load_error("gma", state, tmp_path / "perturbed.pth")
    assert "missing keys (1): update_block.aggregator.gamma" in message
    assert "unexpected keys (1): update_block.aggregator.project.weight" in message
    assert ("shape mismatches (1): att.to_qk.weight (file (512, 128, 1, 1), "
            "model (256, 128, 1, 1))") in message


def test_a_raft_file_is_not_a_gma_file(tmp_path):
    state = build_model("raft").network.state_dict()
    path = tmp_path / "raft.pth"
    torch.save(state, path)
    with pytest.raises(FormatError, match="missing keys .*update_block.aggregator"):
        get_model("gma", checkpoint=path)


# -- the global motion aggregation ---------------------------------------------------------------

def test_attention_and_aggregation_against_a_naive_loop():
    """Pixel i (row-major) attends to pixel j with softmax_j(<q_i, k_j> / sqrt(128)); the
    aggregate adds gamma * sum_j a_ij v_j to the features."""
    torch.manual_seed(0)
    h, w = 3, 4
    context = torch.randn(1, 128, h, w, dtype=torch.float64)
    features = torch.randn(1, 128, h, w, dtype=torch.float64)
    att = ContextAttention().double()
    agg = MotionAggregator().double()
    with torch.no_grad():
        agg.gamma.fill_(0.3)
        attention = att(context)
        out = agg(attention, features)
    with torch.no_grad():
        qk = torch.nn.functional.conv2d(context, att.to_qk.weight)[0]
        v = torch.nn.functional.conv2d(features, agg.to_v.weight)[0].reshape(128, -1)
    q, k = qk[:128].reshape(128, -1), qk[128:].reshape(128, -1)
    f = features[0].reshape(128, -1)
    for i in range(h * w):
        logits = torch.tensor([float(q[:, i] @ k[:, j]) / 128 ** 0.5 for j in range(h * w)],
                              dtype=torch.float64)
        weights = torch.exp(logits - logits.max())
        weights = weights / weights.sum()
        assert torch.allclose(attention[0, i], weights, atol=1e-12)
        expected = f[:, i] + 0.3 * sum(weights[j] * v[:, j] for j in range(h * w))
        assert torch.allclose(out[0].reshape(128, -1)[:, i], expected, atol=1e-10)


def test_aggregation_changes_the_flow():
    model = build_model("gma", iters=2)
    x1, x2 = torch.rand(2, 1, 3, 64, 64).unbind(0)
    with torch.no_grad():
        plain = model(x1, x2)
        model.network.update_block.aggregator.gamma.fill_(1.0)
        aggregated = model(x1, x2)
    assert not torch.allclose(plain, aggregated)


# -- the contract --------------------------------------------------------------------------------

@pytest.mark.parametrize("size", [(37, 45), (67, 93)])
def test_flow_comes_back_at_input_size(size):
    assert_flow_at_input_size(build_model("gma", iters=2), size)


def test_input_gradients_are_finite_and_non_zero():
    model = build_model("gma", iters=3).requires_grad_(False)
    model.network.update_block.aggregator.gamma.fill_(0.5)
    assert_gradient_reaches_both_images(model, (65, 71))


def test_gradient_checkpointing_gives_the_same_gradient():
    torch.manual_seed(0)
    plain = build_model("gma", iters=2)
    plain.network.update_block.aggregator.gamma.data.fill_(0.5)
    recomputing = build_model("gma", iters=2, gradient_checkpointing=True)
    recomputing.load_state_dict(plain.state_dict())
    x1, x2 = random_frames(1, (64, 64))
    grads = [input_gradient(model, x1, x2) for model in (plain, recomputing)]
    # Equal up to float32 rounding (the recomputation may add in another order). The chain of
    # sums forward (tests/numerics.py): RAFT's 14 encoder convolutions, the correlation, the
    # context attention (2), 12 per step (lookup, motion encoder, aggregation, the GRU's four
    # convolutions in a chain, the flow head), the convex upsampling (2); then back. The
    # longest: the GRU's 1 x 5 convolutions over 512 channels.
    assert_float32_close(grads[1], grads[0], rounding_k(2 * (14 + 1 + 2 + 12 * 2 + 2), 512 * 5))


def test_default_iterations_are_the_papers():
    assert build_model("gma").iters == 6
    assert build_model("gma", iters=32).iters == 32


# -- named checkpoints ---------------------------------------------------------------------------

def test_named_checkpoints_and_the_default():
    from weathergen.models import available_checkpoints

    assert set(available_checkpoints("gma")) == {"gma-chairs", "gma-things", "gma-sintel",
                                                  "gma-kitti"}


def test_missing_named_checkpoint_says_which_file_to_put_where(tmp_path, monkeypatch):
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    with pytest.raises(ConfigError) as err:
        get_model("gma")  # default: the Sintel checkpoint, as the paper attacks it
    message = str(err.value)
    assert str(tmp_path / "models" / "gma-sintel.pth") in message
    assert "github.com/zacjiang/GMA" in message and "checkpoints/gma-sintel.pth" in message
    assert "\n" not in message


def test_download_of_a_single_file_lands_in_the_cache(tmp_path, monkeypatch):
    state, _ = random_release("gma")
    payload = io.BytesIO()
    torch.save(state, payload)
    requested = serve(monkeypatch, payload.getvalue())
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    model = get_model("gma-kitti", download=True, iters=1)
    assert requested and requested[0].endswith("/checkpoints/gma-kitti.pth")
    assert sorted(p.name for p in (tmp_path / "models").iterdir()) == ["gma-kitti.pth"]
    assert torch.equal(model.network.att.to_qk.weight, state["module.att.to_qk.weight"])


# -- the command line ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def random_gma_file(tmp_path_factory):
    state, _ = random_release("gma")
    return saved(state, tmp_path_factory.mktemp("gma") / "random-gma.pth")


@pytest.mark.slow
def test_attack_and_evaluate_run_with_gma(random_gma_file, tmp_path):
    model = ["--model", "gma", "--checkpoint", random_gma_file, "--iters", "1"]
    *_, result = attack_then_evaluate(model, tiny_sintel(tmp_path / "sintel"), tmp_path)
    assert result["model"] == "gma" and len(result["pairs"]) == 1
