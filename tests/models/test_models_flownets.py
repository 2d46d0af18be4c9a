"""SpyNet (both forms), FlowNetC, FlowNetCRobust and FlowNet2: the released checkpoints' layouts,
strict loading, the contract (sizes, gradients), and their parts (correlation, warping, channel
norm) against direct implementations. SpyNet's per-level files and its own parts:
test_models_spynet.py."""

from __future__ import annotations

import math

import pytest
import torch
from model_checks import (assert_gradient_reaches_both_images, batch_and_alone, input_gradient,
                          random_frames, serve)
from numerics import assert_float32_close, rounding_k

from weathergen.errors import ConfigError, FormatError
from weathergen.models import build_model, get_model
from weathergen.models.flownet_parts import channel_norm, correlation, warp

ARCHS = ["spynet", "spynet-sniklaus", "flownetc", "flownetcrobust", "flownet2"]


# -- the released checkpoints' key names and shapes, written from the architectures -----------

def _conv(name, cout, cin, k, bias=True):
    keys = {f"{name}.weight": (cout, cin, k, k)}
    if bias:
        keys[f"{name}.bias"] = (cout,)
    return keys


def _deconv(name, cin, cout, bias=True):
    keys = {f"{name}.weight": (cin, cout, 4, 4)}
    if bias:
        keys[f"{name}.bias"] = (cout,)
    return keys


def _decoder(prefix="", deconv_bias=True, upsampler_bias=True):
    """FlowNetS/C's refinement: deconv5..2, predict_flow6..2, upsampled_flow6_to_5..3_to_2."""
    keys = {}
    for name, cin, cout in [("deconv5", 1024, 512), ("deconv4", 1026, 256),
                            ("deconv3", 770, 128), ("deconv2", 386, 64)]:
        keys.update(_deconv(f"{prefix}{name}.0", cin, cout, deconv_bias))
    for level, cin in [(6, 1024), (5, 1026), (4, 770), (3, 386), (2, 194)]:
        keys.update(_conv(f"{prefix}predict_flow{level}", 2, cin, 3))
    for a in (6, 5, 4, 3):
        keys.update(_deconv(f"{prefix}upsampled_flow{a}_to_{a - 1}", 2, 2, upsampler_bias))
    return keys


def _middle(prefix=""):
    """conv_redir ... conv6_1 of FlowNetC (after the Siamese encoder)."""
    keys = {}
    for name, cout, cin, k in [("conv_redir", 32, 256, 1), ("conv3_1", 256, 473, 3),
                               ("conv4", 512, 256, 3), ("conv4_1", 512, 512, 3),
                               ("conv5", 512, 512, 3), ("conv5_1", 512, 512, 3),
                               ("conv6", 1024, 512, 3), ("conv6_1", 1024, 1024, 3)]:
        keys.update(_conv(f"{prefix}{name}.0", cout, cin, k))
    return keys


def flownetc_keys(prefix=""):
    """FlowNet2-C_checkpoint.pth.tar (NVIDIA flownet2-pytorch): every layer with a bias."""
    keys = {}
    for name, cout, cin, k in [("conv1", 64, 3, 7), ("conv2", 128, 64, 5), ("conv3", 256, 128, 5)]:
        keys.update(_conv(f"{prefix}{name}.0", cout, cin, k))
    keys.update(_middle(prefix))
    keys.update(_decoder(prefix, deconv_bias=True, upsampler_bias=True))
    return keys


def flownetcrobust_keys():
    """RobustFlowNetC.pth (Schrodi et al.): convs1/2/3 stages of 1 strided + 3 plain convs,
    no biases in the transposed convolutions."""
    keys = {}
    for stage, cin, cout, k0 in [(1, 3, 64, 7), (2, 64, 128, 3), (3, 128, 256, 3)]:
        keys.update(_conv(f"convs{stage}.0.0", cout, cin, k0))
        for i in (1, 2, 3):
            keys.update(_conv(f"convs{stage}.{i}.0", cout, cout, 3))
    keys.update(_middle())
    keys.update(_decoder(deconv_bias=False, upsampler_bias=False))
    return keys


def flownets_keys(prefix):
    keys = {}
    for name, cout, cin, k in [("conv1", 64, 12, 7), ("conv2", 128, 64, 5), ("conv3", 256, 128, 5),
                               ("conv3_1", 256, 256, 3), ("conv4", 512, 256, 3),
                               ("conv4_1", 512, 512, 3), ("conv5", 512, 512, 3),
                               ("conv5_1", 512, 512, 3), ("conv6", 1024, 512, 3),
                               ("conv6_1", 1024, 1024, 3)]:
        keys.update(_conv(f"{prefix}{name}.0", cout, cin, k))
    keys.update(_decoder(prefix, deconv_bias=True, upsampler_bias=False))
    return keys


def flownetsd_keys(prefix):
    keys = {}
    for name, cout, cin in [("conv0", 64, 6), ("conv1", 64, 64), ("conv1_1", 128, 64),
                            ("conv2", 128, 128), ("conv2_1", 128, 128), ("conv3", 256, 128),
                            ("conv3_1", 256, 256), ("conv4", 512, 256), ("conv4_1", 512, 512),
                            ("conv5", 512, 512), ("conv5_1", 512, 512), ("conv6", 1024, 512),
                            ("conv6_1", 1024, 1024)]:
        keys.update(_conv(f"{prefix}{name}.0", cout, cin, 3))
    for name, cin, cout in [("deconv5", 1024, 512), ("deconv4", 1026, 256),
                            ("deconv3", 770, 128), ("deconv2", 386, 64)]:
        keys.update(_deconv(f"{prefix}{name}.0", cin, cout))
    for name, cout, cin in [("inter_conv5", 512, 1026), ("inter_conv4", 256, 770),
                            ("inter_conv3", 128, 386), ("inter_conv2", 64, 194)]:
        keys.update(_conv(f"{prefix}{name}.0", cout, cin, 3))
    for level, cin in [(6, 1024), (5, 512), (4, 256), (3, 128), (2, 64)]:
        keys.update(_conv(f"{prefix}predict_flow{level}", 2, cin, 3))
    for a in (6, 5, 4, 3):
        keys.update(_deconv(f"{prefix}upsampled_flow{a}_to_{a - 1}", 2, 2))
    return keys


def fusion_keys(prefix):
    keys = {}
    for name, cout, cin in [("conv0", 64, 11), ("conv1", 64, 64), ("conv1_1", 128, 64),
                            ("conv2", 128, 128), ("conv2_1", 128, 128)]:
        keys.update(_conv(f"{prefix}{name}.0", cout, cin, 3))
    keys.update(_deconv(f"{prefix}deconv1.0", 128, 32))
    keys.update(_deconv(f"{prefix}deconv0.0", 162, 16))
    keys.update(_conv(f"{prefix}inter_conv1.0", 32, 162, 3))
    keys.update(_conv(f"{prefix}inter_conv0.0", 16, 82, 3))
    for level, cin in [(2, 128), (1, 32), (0, 16)]:
        keys.update(_conv(f"{prefix}predict_flow{level}", 2, cin, 3))
    keys.update(_deconv(f"{prefix}upsampled_flow2_to_1", 2, 2))
    keys.update(_deconv(f"{prefix}upsampled_flow1_to_0", 2, 2))
    return keys


def flownet2_keys():
    """FlowNet2_checkpoint.pth.tar: the five sub-networks under their attribute names."""
    return {**flownetc_keys("flownetc."), **flownets_keys("flownets_1."),
            **flownets_keys("flownets_2."), **flownetsd_keys("flownets_d."),
            **fusion_keys("flownetfusion.")}


def spynet_keys():
    """The authors' PyTorch module and network-sintel-final.pytorch (the PyTorch port): six
    levels of five 7x7 convolutions."""
    keys = {}
    for level in range(6):
        for index, (cout, cin) in zip((0, 2, 4, 6, 8),
                                      [(32, 8), (64, 32), (32, 64), (16, 32), (2, 16)]):
            keys.update(_conv(f"moduleBasic.{level}.moduleBasic.{index}", cout, cin, 7))
    return keys


EXPECTED = {"spynet": spynet_keys, "spynet-sniklaus": spynet_keys, "flownetc": flownetc_keys,
            "flownetcrobust": flownetcrobust_keys, "flownet2": flownet2_keys}
PARAMETERS = {"flownetc": 39_175_298, "flownet2": 162_518_834}  # as the release states

_MODELS: dict = {}


def meta_model(arch):
    """The architecture without allocating its weights (names and shapes only)."""
    with torch.device("meta"):
        return build_model(arch)


def model(arch):
    """One random-weight model per architecture for this module (FlowNet2 is large), drawn
    from seed 0 without touching the global generator: what a test draws after calling this
    does not depend on whether an earlier test built the model."""
    if arch not in _MODELS:
        with torch.random.fork_rng():
            torch.manual_seed(0)
            _MODELS[arch] = build_model(arch).requires_grad_(False)
    return _MODELS[arch]


@pytest.mark.parametrize("arch", ARCHS)
def test_state_dict_has_the_released_names_and_shapes(arch):
    state = meta_model(arch).network.state_dict()
    got = {k: tuple(v.shape) for k, v in state.items()}
    expected = EXPECTED[arch]()
    assert sorted(set(got) - set(expected)) == [] and sorted(set(expected) - set(got)) == []
    assert got == expected
    if arch in PARAMETERS:
        assert sum(math.prod(s) for s in expected.values()) == PARAMETERS[arch]


# -- strict loading -----------------------------------------------------------------------------

@pytest.mark.parametrize("arch", ARCHS)
def test_released_layout_loads_with_or_without_module_prefix(arch):
    # Names and shapes are checked on weightless (meta) models; values below for SpyNet.
    state = meta_model(arch).network.state_dict()
    for file_state in (state, {"module." + k: v for k, v in state.items()}):
        meta_model(arch).load_checkpoint(file_state, source="file.pth", what=arch)


@pytest.mark.parametrize("arch", ARCHS)
def test_mismatching_checkpoint_fails_listing_what_did_not_match(arch):
    state = dict(meta_model(arch).network.state_dict())
    renamed, reshaped = sorted(state)[0], sorted(state)[-1]
    state["renamed." + renamed] = state.pop(renamed)
    shape = state[reshaped].shape
    state[reshaped] = torch.zeros(*shape[:-1], shape[-1] + 1, device="meta")
    with pytest.raises(FormatError) as err:
        meta_model(arch).load_checkpoint(state, source="bad.pth", what=arch)
    message = str(err.value)
    assert "bad.pth" in message
    assert f"missing keys (1): {renamed}" in message
    assert f"unexpected keys (1): renamed.{renamed}" in message
    assert f"shape mismatches (1): {reshaped}" in message


def _state(arch):
    return {k: v.clone() for k, v in model(arch).network.state_dict().items()}


def test_training_checkpoint_file_loads_through_get_model(tmp_path):
    """NVIDIA's files are {'epoch', 'state_dict', 'best_EPE'} dicts; the weights are used
    (shown with SpyNet's small state dict: the unwrapping does not depend on the network)."""
    state = _state("spynet")
    path = tmp_path / "checkpoint.pth.tar"
    torch.save({"epoch": 0, "state_dict": {"module." + k: v for k, v in state.items()},
                "best_EPE": 1e10}, path)
    loaded = get_model("spynet", checkpoint=path)
    assert all(torch.equal(loaded.network.state_dict()[k], v) for k, v in state.items())
    assert not any(p.requires_grad for p in loaded.parameters())


def test_spynet_file_of_the_ports_current_naming_loads(tmp_path):
    state = _state("spynet-sniklaus")
    path = tmp_path / "spynet.pth"
    torch.save({k.replace("moduleBasic", "netBasic"): v for k, v in state.items()}, path)
    loaded = get_model("spynet-sniklaus", checkpoint=path)
    assert all(torch.equal(loaded.network.state_dict()[k], v) for k, v in state.items())


@pytest.mark.parametrize("name, where", [
    ("spynet-sintel-final", "modelL1_F.t7 ... modelL6_F.t7 at "
                            "https://raw.githubusercontent.com/anuragranj/spynet/"
                            "7c4a3f7d1a5879a50361fff3e1b8fa35ec397fcd/models/"),
    ("spynet-chairs-clean", "modelL1_4.t7 ... modelL5_4.t7 at "),
    ("spynet-sniklaus-sintel-final", "http://content.sniklaus.com/github/pytorch-spynet/"
                                     "network-sintel-final.pytorch"),
    ("flownetcrobust", "cvpr22_adv_flow/RobustFlowNetC.pth"),
    ("flownet2", "FlowNet2_checkpoint.pth.tar at https://drive.google.com/"),
    ("flownetc", "FlowNet2-C_checkpoint.pth.tar at https://drive.google.com/"),
])
def test_missing_named_checkpoint_says_which_file_to_put_where(name, where, tmp_path,
                                                               monkeypatch):
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    with pytest.raises(ConfigError) as err:
        get_model(name)
    message = str(err.value)
    assert str(tmp_path / "models" / f"{name}.pth") in message
    assert where in message
    assert "\n" not in message


def test_spynet_sniklaus_checkpoint_downloads_as_a_plain_file(tmp_path, monkeypatch):
    import io

    buf = io.BytesIO()
    torch.save(_state("spynet-sniklaus"), buf)
    asked = serve(monkeypatch, buf.getvalue())
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    loaded = get_model("spynet-sniklaus-sintel-final", download=True)
    assert asked == ["http://content.sniklaus.com/github/pytorch-spynet/"
                     "network-sintel-final.pytorch"]
    assert sorted(p.name for p in (tmp_path / "models").iterdir()) == [
        "spynet-sniklaus-sintel-final.pth"]
    assert loaded.architecture == "spynet-sniklaus"


# -- the contract ---------------------------------------------------------------------------------

@pytest.mark.parametrize("arch", ARCHS)
def test_flow_at_odd_input_size_with_finite_non_zero_input_gradients(arch):
    net = model(arch)
    torch.manual_seed(1)
    flow = assert_gradient_reaches_both_images(net, (37, 53))
    assert flow.shape == (1, 2, 37, 53)
    assert torch.isfinite(flow).all()


def test_batch_elements_are_independent():
    in_batch, alone = batch_and_alone(model("flownetc"), (40, 70))
    # Equal up to float32 rounding (a batch of two may add in another order): 17 sums in a chain
    # (16 convolutions and the correlation), the longest over 1024 x 3 x 3 terms.
    assert_float32_close(in_batch, alone, rounding_k(17, 1024 * 9))


#: (sums in the forward chain, terms of the longest) of the networks checkpointing is tested on,
#: at 32 x 64 (tests/numerics.py).
CHECKPOINTED_CHAINS = {"spynet": (6 * 7, 64 * 49), "spynet-sniklaus": (2 * 7, 64 * 49),
                       "flownetc": (17, 1024 * 9)}


@pytest.mark.parametrize("arch", ["spynet", "spynet-sniklaus", "flownetc"])
def test_gradient_checkpointing_gives_the_same_gradient(arch):
    plain = model(arch)
    recomputing = build_model(arch, gradient_checkpointing=True)
    recomputing.load_state_dict(plain.state_dict())
    x1, x2 = random_frames(1, (32, 64))  # port's SpyNet: two levels; paper's: six
    grads = [input_gradient(m, x1, x2) for m in (plain, recomputing)]
    # Equal up to float32 rounding: the recomputation may add in another order (oneDNN's AVX-512
    # convolutions do). The gradient passes the forward chain of sums and then the same chain
    # back: per SpyNet level five 7x7 convolutions over 64 channels, the warp and the upsampling;
    # FlowNetC's 16 convolutions and its correlation, the longest over 1024 x 3 x 3 terms.
    sums, terms = CHECKPOINTED_CHAINS[arch]
    assert_float32_close(grads[1], grads[0], rounding_k(2 * sums, terms))


@pytest.mark.parametrize("arch", ["flownetc"])
def test_flownet2_family_ignores_a_common_brightness_offset(arch):
    """Their input normalisation (FlowNet2's too: the same function) subtracts the mean of
    both frames: adding the same constant to both frames leaves the flow unchanged."""
    x1, x2 = random_frames(1, (64, 64))
    with torch.no_grad():
        a = model(arch)(x1 * 0.8, x2 * 0.8)
        b = model(arch)(x1 * 0.8 + 0.15, x2 * 0.8 + 0.15)
        c = model(arch)(x1 * 0.8 + 0.15, x2 * 0.8)  # an offset on one frame only
    assert torch.allclose(a, b, atol=1e-4 * (1 + a.abs().max().item()))
    assert not torch.allclose(a, c, atol=1e-4 * (1 + a.abs().max().item()))


def test_spynet_pyramid_doubles_and_accumulates_the_flow():
    """Each level's network adds its output to the doubled, upsampled flow of the coarser
    level. With every weight zero and the last biases (1, -0.5), each level adds (1, -0.5);
    in the port's pyramid a 64 x 96 frame has three levels, so the flow is (1 + 2 + 4) x
    (1, -0.5) (the paper's: test_models_spynet.py)."""
    spynet = build_model("spynet-sniklaus")
    with torch.no_grad():
        for p in spynet.network.parameters():
            p.zero_()
        for level in spynet.network.moduleBasic:
            level.moduleBasic[8].bias.copy_(torch.tensor([1.0, -0.5]))
        flow = spynet(torch.rand(1, 3, 64, 96), torch.rand(1, 3, 64, 96))
    # 64 x 96 -> 32 x 48 (still > 32 wide) -> 16 x 24: three levels.
    assert torch.allclose(flow[0, 0], torch.full((64, 96), 7.0))
    assert torch.allclose(flow[0, 1], torch.full((64, 96), -3.5))


@pytest.mark.parametrize("arch, scale", [("flownetc", 20.0), ("flownetcrobust", 1.0)])
def test_flownetc_output_units(arch, scale):
    """FlowNetC predicts 1/20 pixels at 1/4 resolution (the adapter multiplies by 20),
    FlowNetCRobust pixels: with every weight zero, the flow is the last layer's bias, scaled."""
    net = build_model(arch)
    with torch.no_grad():
        for p in net.network.parameters():
            p.zero_()
        net.network.predict_flow2.bias.copy_(torch.tensor([0.5, -0.25]))
        flow = net(torch.rand(1, 3, 50, 70), torch.rand(1, 3, 50, 70))
    assert torch.allclose(flow[0, 0], torch.full((50, 70), 0.5 * scale))
    assert torch.allclose(flow[0, 1], torch.full((50, 70), -0.25 * scale))


# -- parts against direct implementations ------------------------------------------------------

def naive_correlation(f1, f2, max_displacement, stride):
    b, c, h, w = f1.shape
    r = max_displacement // stride
    n = 2 * r + 1
    out = torch.zeros(b, n * n, h, w, dtype=f1.dtype)
    for i in range(n):
        for j in range(n):
            dy, dx = (i - r) * stride, (j - r) * stride
            for y in range(h):
                for x in range(w):
                    if 0 <= y + dy < h and 0 <= x + dx < w:
                        products = f1[:, :, y, x] * f2[:, :, y + dy, x + dx]
                        out[:, i * n + j, y, x] = products.sum(1) / c
    return out


@pytest.mark.parametrize("block, chunk", [(1, 1), (3, 1000), (32, 1 << 24)])
def test_correlation_matches_a_naive_loop(block, chunk):
    """Any split into column blocks and chunks of displacement rows gives the same values."""
    torch.manual_seed(2)
    f1, f2 = torch.randn(2, 2, 5, 7, 9, dtype=torch.float64).unbind(0)
    got = correlation(f1, f2, max_displacement=4, stride=2, block=block, chunk_elements=chunk)
    assert got.shape == (2, 25, 7, 9)
    assert torch.allclose(got, naive_correlation(f1, f2, 4, 2), atol=1e-12)
    got1 = correlation(f1, f2, max_displacement=3, stride=1, block=block, chunk_elements=chunk)
    assert torch.allclose(got1, naive_correlation(f1, f2, 3, 1), atol=1e-12)


def test_correlation_gradient():
    torch.manual_seed(3)
    f1, f2 = torch.randn(2, 1, 2, 3, 4, dtype=torch.float64).unbind(0)
    f1.requires_grad_(True)
    f2.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda a, b: correlation(a, b, max_displacement=2, stride=2, block=3,
                                 chunk_elements=30), (f1, f2))


def naive_resample(image, flow):
    """FlowNet2's Resample2d: the four corners clamped into the image one by one."""
    b, c, h, w = image.shape
    out = torch.zeros_like(image)
    for n in range(b):
        for y in range(h):
            for x in range(w):
                xf = x + flow[n, 0, y, x].item()
                yf = y + flow[n, 1, y, x].item()
                alpha, beta = xf - math.floor(xf), yf - math.floor(yf)
                xl, xr = [min(max(v, 0), w - 1) for v in (math.floor(xf), math.floor(xf) + 1)]
                yt, yb = [min(max(v, 0), h - 1) for v in (math.floor(yf), math.floor(yf) + 1)]
                out[n, :, y, x] = ((1 - alpha) * (1 - beta) * image[n, :, yt, xl]
                                   + alpha * (1 - beta) * image[n, :, yt, xr]
                                   + (1 - alpha) * beta * image[n, :, yb, xl]
                                   + alpha * beta * image[n, :, yb, xr])
    return out


def test_warp_matches_resample2d_including_outside_the_image():
    torch.manual_seed(4)
    image = torch.rand(2, 3, 6, 7, dtype=torch.float64)
    flow = 4.0 * torch.randn(2, 2, 6, 7, dtype=torch.float64)  # many points fall outside
    assert torch.allclose(warp(image, flow), naive_resample(image, flow), atol=1e-12)
    # Integer flow inside the image picks pixels exactly.
    shift = torch.zeros(1, 2, 6, 7, dtype=torch.float64)
    shift[:, 0] = 1.0
    assert torch.allclose(warp(image[:1], shift)[..., :-1], image[:1, :, :, 1:], atol=1e-12)


def test_channel_norm_and_its_gradient_at_zero():
    x = torch.tensor([[[[3.0, 0.0]], [[4.0, 0.0]]]], requires_grad=True)  # (1, 2, 1, 2)
    norm = channel_norm(x)
    assert norm.shape == (1, 1, 1, 2)
    assert torch.allclose(norm.detach(), torch.tensor([[[[5.0, 0.0]]]]))
    norm.sum().backward()
    assert torch.isfinite(x.grad).all()
    assert torch.allclose(x.grad[0, :, 0, 0], torch.tensor([0.6, 0.8]))
    assert torch.equal(x.grad[0, :, 0, 1], torch.zeros(2))
