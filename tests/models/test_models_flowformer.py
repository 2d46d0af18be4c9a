"""FlowFormer behind the model contract: the released key layout (Twins-SVT in timm's layout, the
cost encoder and decoder), strict loading, building blocks against naive computations, shapes,
gradients, batch independence, named checkpoints and the CLI."""

from __future__ import annotations

import math

import pytest
import torch
from model_checks import (assert_flow_at_input_size, assert_gradient_reaches_both_images,
                          assert_loads_strictly, attack_then_evaluate, batch_and_alone,
                          input_gradient, load_error, random_frames, random_release, saved,
                          tiny_sintel)
from numerics import assert_float32_close, rounding_k

from weathergen.errors import ConfigError
from weathergen.models import build_model, get_model
from weathergen.models.flowformer import cost_window, position_encoding
from model_layouts import gma_attention_layout, gma_update_layout

SIZE = (40, 48)  # the smallest size the model sees (multiple of 8, at least 32)


def flowformer_sums(iters):
    """FlowFormer's chain of sums, forward (tests/numerics.py): the Twins encoder's (two patch
    embeddings, four blocks of attention (4) and MLP (2), the 1x1 convolution: 27), the cost
    volume, the cost encoder's (three strided convolutions, the summary's attention and MLP,
    three rounds of self and pixel attention: 45), 18 per decoder step (cost query,
    cross-attention, GMA's update), the convex upsampling (2). The longest sum: an MLP's
    second layer, 4 x 256 terms."""
    return 27 + 1 + 45 + 18 * iters + 2


FLOWFORMER_TERMS = 4 * 256


# -- the released key layout, written from the published architecture --------------------------

def _linear(out: dict, name: str, o: int, i: int):
    out[f"{name}.weight"] = (o, i)
    out[f"{name}.bias"] = (o,)


def _norm(out: dict, name: str, c: int):
    out[f"{name}.weight"] = (c,)
    out[f"{name}.bias"] = (c,)


def twins_layout(prefix: str) -> dict:
    """timm's Twins-SVT-large with stages 3 and 4 and the classifier removed: per stage a patch
    embedding (4x4 then 2x2 conv + norm), a locally-grouped block (qkv) and a global sub-sampled
    block (q, kv, sr conv 8x8 then 4x4 + norm), a depth-wise position conv; the final norm of
    the full model (1024 channels) stays."""
    out = {}
    in_chans, patch = 3, 4
    for s, (d, sr) in enumerate([(128, 8), (256, 4)]):
        p = f"{prefix}svt."
        out[f"{p}patch_embeds.{s}.proj.weight"] = (d, in_chans, patch, patch)
        out[f"{p}patch_embeds.{s}.proj.bias"] = (d,)
        _norm(out, f"{p}patch_embeds.{s}.norm", d)
        for j in (0, 1):
            b = f"{p}blocks.{s}.{j}"
            _norm(out, f"{b}.norm1", d)
            if j == 0:
                _linear(out, f"{b}.attn.qkv", 3 * d, d)
            else:
                _linear(out, f"{b}.attn.q", d, d)
                _linear(out, f"{b}.attn.kv", 2 * d, d)
                out[f"{b}.attn.sr.weight"] = (d, d, sr, sr)
                out[f"{b}.attn.sr.bias"] = (d,)
                _norm(out, f"{b}.attn.norm", d)
            _linear(out, f"{b}.attn.proj", d, d)
            _norm(out, f"{b}.norm2", d)
            _linear(out, f"{b}.mlp.fc1", 4 * d, d)
            _linear(out, f"{b}.mlp.fc2", d, 4 * d)
        out[f"{p}pos_block.{s}.proj.0.weight"] = (d, 1, 3, 3)
        out[f"{p}pos_block.{s}.proj.0.bias"] = (d,)
        in_chans, patch = d, 2
    _norm(out, f"{prefix}svt.norm", 1024)
    return out


def _attention_layer(out: dict, p: str, dim: int, kv_dim: int, proj_in: int):
    _norm(out, f"{p}.norm1", dim)
    _norm(out, f"{p}.norm2", dim)
    _linear(out, f"{p}.q", dim, dim)
    _linear(out, f"{p}.k", dim, kv_dim)
    _linear(out, f"{p}.v", dim, kv_dim)
    _linear(out, f"{p}.proj", dim, proj_in)
    _linear(out, f"{p}.ffn.0", dim, dim)
    _linear(out, f"{p}.ffn.3", dim, dim)


def cost_encoder_layout(prefix: str) -> dict:
    out = {}
    pe = f"{prefix}patch_embed"
    for idx, (o, i) in zip((0, 2, 4), [(16, 1), (32, 16), (64, 32)]):
        out[f"{pe}.proj.{idx}.weight"] = (o, i, 6, 6)
        out[f"{pe}.proj.{idx}.bias"] = (o,)
    for idx in (0, 2):
        out[f"{pe}.ffn_with_coord.{idx}.weight"] = (128, 128, 1, 1)
        out[f"{pe}.ffn_with_coord.{idx}.bias"] = (128,)
    _norm(out, f"{pe}.norm", 128)
    out[f"{prefix}latent_tokens"] = (1, 8, 128)
    _attention_layer(out, f"{prefix}input_layer", 128, 128, 128)
    for layer in range(3):
        _attention_layer(out, f"{prefix}encoder_layers.{layer}", 128, 128, 128)
        for kind in ("local_block", "global_block"):
            b = f"{prefix}vertical_encoder_layers.{layer}.{kind}"
            _norm(out, f"{b}.norm1", 128)
            _norm(out, f"{b}.norm2", 128)
            _linear(out, f"{b}.mlp.fc1", 512, 128)
            _linear(out, f"{b}.mlp.fc2", 128, 512)
            _linear(out, f"{b}.attn.context_proj", 64, 256)
            _linear(out, f"{b}.attn.q", 128, 192)
            _linear(out, f"{b}.attn.proj", 128, 128)
            _linear(out, f"{b}.attn.v", 128, 128)
            if kind == "local_block":
                _linear(out, f"{b}.attn.k", 128, 192)
            else:
                _linear(out, f"{b}.attn.k", 128, 128)
                out[f"{b}.attn.sr_key.weight"] = (128, 192, 4, 4)
                out[f"{b}.attn.sr_key.bias"] = (128,)
                out[f"{b}.attn.sr_value.weight"] = (128, 128, 4, 4)
                out[f"{b}.attn.sr_value.bias"] = (128,)
                _norm(out, f"{b}.attn.norm", 128)
    return out


def decoder_layout(prefix: str) -> dict:
    out = {f"{prefix}flow_token_encoder.0.weight": (64, 81, 1, 1),
           f"{prefix}flow_token_encoder.0.bias": (64,),
           f"{prefix}flow_token_encoder.2.weight": (64, 64, 1, 1),
           f"{prefix}flow_token_encoder.2.bias": (64,),
           f"{prefix}proj.weight": (256, 256, 1, 1), f"{prefix}proj.bias": (256,)}
    _attention_layer(out, f"{prefix}decoder_layer.cross_attend", 64, 128, 128)
    out.update(gma_update_layout(f"{prefix}update_block.", 64 + 81))
    out.update(gma_attention_layout(f"{prefix}att."))
    return out


FLOWFORMER_LAYOUT = {**twins_layout("context_encoder."),
                     **twins_layout("memory_encoder.feat_encoder."),
                     "memory_encoder.channel_convertor.weight": (256, 256, 1, 1),
                     **cost_encoder_layout("memory_encoder.cost_perceiver_encoder."),
                     **decoder_layout("memory_decoder.")}


def test_state_dict_has_the_released_names_and_shapes():
    state = build_model("flowformer").network.state_dict()
    assert {k: tuple(v.shape) for k, v in state.items()} == FLOWFORMER_LAYOUT
    params = sum(p.numel() for p in build_model("flowformer").parameters())
    assert params == 16_168_113  # FlowFormer's published size, "16.1M" without unused parts


# -- strict loading ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def released():
    return random_release("flowformer", seed=3)


@pytest.fixture(scope="module")
def random_file(released, tmp_path_factory):
    return saved(released[0], tmp_path_factory.mktemp("flowformer") / "random-flowformer.pth")


def test_a_saved_random_model_loads_strictly(released, random_file, tmp_path):
    state, source = released
    assert_loads_strictly("flowformer", random_file, state, source, "module.", SIZE)
    # Without the DataParallel prefix too.
    bare = tmp_path / "bare.pth"
    torch.save({k[len("module."):]: v for k, v in state.items()}, bare)
    assert get_model("flowformer", checkpoint=bare).iters == 32


def test_a_perturbed_file_fails_listing_what_does_not_match(released, tmp_path):
    state = dict(released[0])
    del state["module.context_encoder.svt.norm.weight"]
    state["module.context_encoder.svt.head.weight"] = torch.zeros(1000, 1024)
    state["module.memory_encoder.cost_perceiver_encoder.latent_tokens"] = torch.zeros(1, 16, 128)
    message = load_error("flowformer", state, tmp_path / "perturbed.pth")
    assert "missing keys (1): context_encoder.svt.norm.weight" in message
    assert "unexpected keys (1): context_encoder.svt.head.weight" in message
    assert ("shape mismatches (1): memory_encoder.cost_perceiver_encoder.latent_tokens "
            "(file (1, 16, 128), model (1, 8, 128))") in message


# -- building blocks -----------------------------------------------------------------------------

def test_position_encoding_values():
    coords = torch.tensor([[3.0, 5.0]], dtype=torch.float64)
    enc = position_encoding(coords, 16)[0]
    for f in range(4):
        a = 3.14 * f / 200  # the trained constants
        assert enc[f].item() == pytest.approx(math.sin(a * 3.0))
        assert enc[4 + f].item() == pytest.approx(math.cos(a * 3.0))
        assert enc[8 + f].item() == pytest.approx(math.sin(a * 5.0))
        assert enc[12 + f].item() == pytest.approx(math.cos(a * 5.0))


def test_cost_window_against_a_naive_lookup():
    """At integer positions, channel a*9 + b holds cost(p -> match + (a-4, b-4)), zero outside."""
    torch.manual_seed(0)
    h, w = 5, 7
    cost = torch.randn(h * w, 1, h, w, dtype=torch.float64)
    flow = torch.randint(-2, 3, (1, 2, h, w)).double()
    ys, xs = torch.meshgrid(torch.arange(h).double(), torch.arange(w).double(), indexing="ij")
    coords = torch.stack([xs, ys])[None] + flow
    out = cost_window(cost, coords, 4)
    assert out.shape == (1, 81, h, w)
    for (y, x) in [(0, 0), (2, 3), (4, 6)]:
        mx, my = int(coords[0, 0, y, x]), int(coords[0, 1, y, x])
        for a in range(9):
            for b in range(9):
                x2, y2 = mx + a - 4, my + b - 4
                expected = cost[y * w + x, 0, y2, x2].item() if 0 <= x2 < w and 0 <= y2 < h else 0
                assert out[0, a * 9 + b, y, x].item() == pytest.approx(expected, abs=1e-12)


# -- the contract --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def small_model():
    torch.manual_seed(0)
    model = build_model("flowformer", iters=2).requires_grad_(False)
    model.network.memory_decoder.update_block.aggregator.gamma.fill_(0.5)
    return model


@pytest.mark.parametrize("size", [(37, 45), (19, 70)])
def test_flow_comes_back_at_input_size(small_model, size):
    assert_flow_at_input_size(small_model, size)


def test_input_gradients_are_finite_and_non_zero(small_model):
    assert_gradient_reaches_both_images(small_model, (37, 45))


def test_gradient_checkpointing_gives_the_same_gradient(monkeypatch):
    import weathergen.models.flowformer as flowformer

    monkeypatch.setattr(flowformer, "SUMMARY_CHUNK", 7)  # recompute the cost maps in chunks
    torch.manual_seed(0)
    model = build_model("flowformer", iters=1)
    x1, x2 = random_frames(1, SIZE)
    grads = []
    for checkpointing in (False, True):
        model.gradient_checkpointing = checkpointing
        grads.append(input_gradient(model, x1, x2))
    # The same up to float32 rounding (the chunked convolutions sum in another order): the
    # chain of sums forward and back.
    assert_float32_close(grads[1], grads[0], rounding_k(2 * flowformer_sums(1), FLOWFORMER_TERMS))


def test_batch_elements_are_independent(small_model):
    # The context of each frame pair meets only that pair's cost tokens.
    in_batch, alone = batch_and_alone(small_model, SIZE, index=1)
    # Equal up to float32 rounding: a batch of two may add in another order.
    assert_float32_close(in_batch, alone, rounding_k(flowformer_sums(2), FLOWFORMER_TERMS))


def test_default_iterations_are_the_authors_evaluation_setting():
    assert build_model("flowformer").iters == 32


# -- named checkpoints ---------------------------------------------------------------------------

def test_named_checkpoints_and_the_offline_message(tmp_path, monkeypatch):
    from weathergen.models import available_checkpoints

    assert set(available_checkpoints("flowformer")) == {
        "flowformer-chairs", "flowformer-things", "flowformer-sintel", "flowformer-kitti"}
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    for download in (False, True):  # no download address: both say where to get the file
        with pytest.raises(ConfigError) as err:
            get_model("flowformer", download=download)
        message = str(err.value)
        assert str(tmp_path / "models" / "flowformer-sintel.pth") in message
        assert "sintel.pth at https://drive.google.com/drive/folders/" in message
        assert "\n" not in message


# -- the command line ----------------------------------------------------------------------------

@pytest.mark.slow
def test_attack_and_evaluate_run_with_flowformer(random_file, tmp_path):
    model = ["--model", "flowformer", "--checkpoint", random_file, "--iters", "1"]
    *_, result = attack_then_evaluate(model, tiny_sintel(tmp_path / "sintel"), tmp_path)
    assert result["model"] == "flowformer" and len(result["pairs"]) == 1
