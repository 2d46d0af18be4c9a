"""The paper's SpyNet (``spynet``): the authors' per-level weight files (Torch7 and the converted
PyTorch files) read strictly, their download packed into one file, the pyramid, and the warping
against a direct implementation. The comparison with the reference implementations on random
weights is in test_models_reference.py; both forms' checkpoint layouts in test_models_flownets.py."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from model_checks import serve
from torch7_files import spynet_level, write_torch7

from weathergen.errors import ConfigError, FormatError, ShapeError
from weathergen.models import build_model, get_model, registry
from weathergen.models.spynet import SPYNET_URL, SpyNet, clamped_grid_warp

SHAPES = [((32, 8, 7, 7), (32,)), ((64, 32, 7, 7), (64,)), ((32, 64, 7, 7), (32,)),
          ((16, 32, 7, 7), (16,)), ((2, 16, 7, 7), (2,))]


def level_weights(level: int, seed: int = 0) -> list:
    """Five random (weight, bias) float32 arrays for one level, different for every level."""
    rng = np.random.default_rng(100 * seed + level)
    return [(rng.normal(0, 0.05, w).astype(np.float32), rng.normal(0, 0.05, b).astype(np.float32))
            for w, b in SHAPES]


def write_torch7_model(folder, letter="F", levels=6, seed=0, **kwargs) -> dict:
    """modelL1_<letter>.t7 ... as the authors saved them; returns the expected state dict."""
    folder.mkdir(parents=True, exist_ok=True)
    state = {}
    for level in range(1, levels + 1):
        convs = level_weights(level, seed)
        write_torch7(folder / f"modelL{level}_{letter}.t7", spynet_level(convs, **kwargs))
        for conv, (w, b) in enumerate(convs):
            state[f"moduleBasic.{level - 1}.moduleBasic.{2 * conv}.weight"] = torch.from_numpy(w)
            state[f"moduleBasic.{level - 1}.moduleBasic.{2 * conv}.bias"] = torch.from_numpy(b)
    return state


def write_tensor_model(folder, letter="F", seed=0) -> dict:
    """The 60 files modelL<n>_<letter>-<k>-weight|bias.pth.tar of the authors' PyTorch code."""
    folder.mkdir(parents=True, exist_ok=True)
    state = {}
    for level in range(1, 7):
        for conv, (w, b) in enumerate(level_weights(level, seed)):
            for part, value in (("weight", w), ("bias", b)):
                torch.save(torch.from_numpy(value), folder / f"modelL{level}_{letter}-{conv + 1}-"
                                                             f"{part}.pth.tar")
                state[f"moduleBasic.{level - 1}.moduleBasic.{2 * conv}.{part}"] = \
                    torch.from_numpy(value)
    return state


def assert_holds(model, state):
    loaded = model.network.state_dict()
    assert sorted(loaded) == sorted(state)
    for key, value in state.items():
        assert torch.equal(loaded[key], value), key


# -- per-level files ------------------------------------------------------------------------------

@pytest.mark.parametrize("layout", [
    dict(),                                                  # one flat storage, cudnn convs
    dict(flat=False, class_name="nn.SpatialConvolution"),    # a tensor each
    dict(wrap=True),                                         # inside a DataParallelTable
])
def test_torch7_level_files_load_from_any_of_them_or_their_folder(tmp_path, layout):
    state = write_torch7_model(tmp_path / "models", **layout)
    for checkpoint in (tmp_path / "models" / "modelL1_F.t7", tmp_path / "models" / "modelL4_F.t7",
                       tmp_path / "models"):
        assert_holds(get_model("spynet", checkpoint=checkpoint), state)


def test_torch7_files_of_spatial_convolution_mm_store_flat_weights(tmp_path):
    folder = tmp_path / "mm"
    state = write_torch7_model(folder, class_name="nn.SpatialConvolutionMM")
    # rewrite level 2 with 2-D weights, as nn.SpatialConvolutionMM keeps them
    convs = [(w.reshape(w.shape[0], -1), b) for w, b in level_weights(2)]
    write_torch7(folder / "modelL2_F.t7", spynet_level(convs, flat=False,
                                                      class_name="nn.SpatialConvolutionMM"))
    assert_holds(get_model("spynet", checkpoint=folder), state)


def test_converted_tensor_files_load_the_same_weights(tmp_path):
    torch7 = write_torch7_model(tmp_path / "t7")
    tensors = write_tensor_model(tmp_path / "pth")
    assert all(torch.equal(torch7[k], tensors[k]) for k in torch7)
    for checkpoint in (tmp_path / "pth" / "modelL3_F-2-bias.pth.tar", tmp_path / "pth"):
        assert_holds(get_model("spynet", checkpoint=checkpoint), tensors)


def test_five_level_models_run_their_fifth_level_twice(tmp_path):
    state = write_torch7_model(tmp_path / "chairs", letter="3", levels=5)
    loaded = get_model("spynet", checkpoint=tmp_path / "chairs" / "modelL1_3.t7")
    for conv in range(5):
        for part in ("weight", "bias"):
            five = state[f"moduleBasic.4.moduleBasic.{2 * conv}.{part}"]
            assert torch.equal(loaded.network.state_dict()[f"moduleBasic.5.moduleBasic."
                                                           f"{2 * conv}.{part}"], five)


def test_packed_state_dict_of_the_authors_module_loads_with_or_without_prefix(tmp_path):
    state = write_torch7_model(tmp_path / "t7")
    for prefix in ("", "module."):
        path = tmp_path / f"packed{prefix}.pth"
        torch.save({prefix + k: v for k, v in state.items()}, path)
        assert_holds(get_model("spynet", checkpoint=path), state)


def _error(checkpoint) -> str:
    with pytest.raises(FormatError) as err:
        get_model("spynet", checkpoint=checkpoint)
    message = str(err.value)
    assert "\n" not in message
    return message


def test_a_missing_level_file_is_named(tmp_path):
    write_torch7_model(tmp_path / "m")
    (tmp_path / "m" / "modelL5_F.t7").unlink()
    message = _error(tmp_path / "m" / "modelL1_F.t7")
    assert message.startswith(str(tmp_path / "m" / "modelL5_F.t7")) and "missing" in message
    write_tensor_model(tmp_path / "p")
    (tmp_path / "p" / "modelL6_F-5-bias.pth.tar").unlink()
    message = _error(tmp_path / "p")
    assert message.startswith(str(tmp_path / "p" / "modelL6_F-5-bias.pth.tar"))
    assert "needs 60 such files" in message


def test_a_level_with_another_number_of_convolutions_is_refused(tmp_path):
    write_torch7_model(tmp_path / "m")
    write_torch7(tmp_path / "m" / "modelL2_F.t7", spynet_level(level_weights(2)[:4]))
    message = _error(tmp_path / "m")
    assert message.startswith(str(tmp_path / "m" / "modelL2_F.t7"))
    assert "holds 4 spatial convolutions, expected 5" in message


def test_a_convolution_of_the_wrong_shape_is_refused(tmp_path):
    write_torch7_model(tmp_path / "m")
    convs = level_weights(3)
    convs[1] = (np.zeros((64, 31, 7, 7), np.float32), convs[1][1])
    write_torch7(tmp_path / "m" / "modelL3_F.t7", spynet_level(convs, flat=False))
    message = _error(tmp_path / "m")
    assert message.startswith(str(tmp_path / "m" / "modelL3_F.t7"))
    assert "convolution 2 has weight and bias of shapes (64, 31, 7, 7) and (64,)" in message
    write_tensor_model(tmp_path / "p")
    torch.save(torch.zeros(3), tmp_path / "p" / "modelL1_F-5-bias.pth.tar")
    message = _error(tmp_path / "p")
    assert message.startswith(str(tmp_path / "p" / "modelL1_F-5-bias.pth.tar"))
    assert "shape (3,), expected (2,)" in message
    torch.save({"bias": torch.zeros(2)}, tmp_path / "p" / "modelL1_F-5-bias.pth.tar")
    assert "expected one tensor, got dict" in _error(tmp_path / "p")


def test_a_folder_with_several_models_asks_for_one_file(tmp_path):
    write_torch7_model(tmp_path / "m", letter="F")
    write_torch7_model(tmp_path / "m", letter="C")
    message = _error(tmp_path / "m")
    assert message.startswith(str(tmp_path / "m"))
    assert "found models: C (torch7), F (torch7)" in message and "modelL1_F.t7" in message
    assert "found models: none" in _error(tmp_path)


def test_a_packed_file_that_does_not_fit_lists_the_keys(tmp_path):
    state = write_torch7_model(tmp_path / "t7")
    state["moduleBasic.6.moduleBasic.0.weight"] = state.pop("moduleBasic.0.moduleBasic.0.weight")
    torch.save(state, tmp_path / "bad.pth")
    message = _error(tmp_path / "bad.pth")
    assert "missing keys (1): moduleBasic.0.moduleBasic.0.weight" in message
    assert "unexpected keys (1): moduleBasic.6.moduleBasic.0.weight" in message


# -- the download --------------------------------------------------------------------------------

def _served_files(tmp_path, monkeypatch, letter, levels):
    """Our random files served at the authors' addresses; the known checksums (of the real
    files) are set aside for the checkpoints of ``letter``."""
    write_torch7_model(tmp_path / "served", letter=letter, levels=levels)
    for name, spec in list(registry._CHECKPOINTS.items()):
        if spec.parts and spec.parts[0].endswith(f"_{letter}.t7"):
            monkeypatch.setitem(registry._CHECKPOINTS, name, replace(spec, part_sha256=()))
    return {SPYNET_URL + p.name: p.read_bytes() for p in (tmp_path / "served").iterdir()}


@pytest.mark.parametrize("name, letter, levels", [("spynet-sintel-final", "F", 6),
                                                  ("spynet-chairs-clean", "4", 5)])
def test_download_fetches_the_level_files_and_caches_them_packed(tmp_path, monkeypatch, name,
                                                                 letter, levels):
    asked = serve(monkeypatch, _served_files(tmp_path, monkeypatch, letter, levels))
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path / "cache"))
    loaded = get_model(name, download=True)
    assert asked == [f"{SPYNET_URL}modelL{n}_{letter}.t7" for n in range(1, levels + 1)]
    cached = tmp_path / "cache" / "models" / f"{name}.pth"
    assert sorted(p.name for p in cached.parent.iterdir()) == [cached.name]
    expected = get_model("spynet", checkpoint=tmp_path / "served" / f"modelL1_{letter}.t7")
    assert_holds(loaded, expected.network.state_dict())
    assert_holds(get_model(name), expected.network.state_dict())     # now from the cache


def test_a_failed_download_leaves_nothing_behind(tmp_path, monkeypatch):
    files = _served_files(tmp_path, monkeypatch, "F", 6)
    del files[SPYNET_URL + "modelL4_F.t7"]
    serve(monkeypatch, files)
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path / "cache"))
    with pytest.raises(ConfigError, match="could not download .*modelL4_F.t7"):
        get_model("spynet", download=True)
    assert list((tmp_path / "cache" / "models").iterdir()) == []


def test_a_downloaded_level_file_with_another_checksum_is_refused(tmp_path, monkeypatch):
    write_torch7_model(tmp_path / "served")
    serve(monkeypatch, {SPYNET_URL + p.name: p.read_bytes()
                        for p in (tmp_path / "served").iterdir()})
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path / "cache"))
    with pytest.raises(ConfigError, match="modelL1_F.t7 has sha256 .*, expected 238ae30d"):
        get_model("spynet-sintel-final", download=True)
    assert list((tmp_path / "cache" / "models").iterdir()) == []


# -- the network ---------------------------------------------------------------------------------

def test_six_levels_double_and_accumulate_the_flow_whatever_the_size():
    """With every weight zero and the last biases (1, -0.5), each level adds (1, -0.5) to the
    doubled flow of the coarser one; the paper's SpyNet always runs six levels, so the flow is
    (1 + 2 + ... + 32) x (1, -0.5) for any frame size (padded to a multiple of 64)."""
    spynet = build_model("spynet")
    with torch.no_grad():
        for p in spynet.network.parameters():
            p.zero_()
        for level in spynet.network.moduleBasic:
            level.moduleBasic[8].bias.copy_(torch.tensor([1.0, -0.5]))
        for size in ((40, 56), (64, 96), (130, 70)):
            flow = spynet(torch.rand(1, 3, *size), torch.rand(1, 3, *size))
            assert torch.allclose(flow[0, 0], torch.full(size, 63.0))
            assert torch.allclose(flow[0, 1], torch.full(size, -31.5))


def test_upsampling_uses_half_pixel_centres():
    """A ramp 0, 1 upsampled with half-pixel centres gives 0, 0.25, 0.75, 1 (corner-aligned:
    0, 1/3, 2/3, 1); the values are doubled (pixels of the finer level)."""
    ramp = torch.tensor([0.0, 1.0]).view(1, 1, 1, 2).expand(1, 2, 2, 2)
    up = SpyNet().upsample(ramp)
    assert torch.allclose(up[0, 0, 0], torch.tensor([0.0, 0.5, 1.5, 2.0]))


def naive_clamped_warp(image, flow):
    """The research code's warp spelled out per pixel: the corner-aligned grid point
    -1 + 2 (x + u) / (W - 1), clamped to [-1, 1], read with half-pixel centres
    (pixel ((g + 1) W - 1) / 2), bilinear, zero outside."""
    b, c, h, w = image.shape
    out = torch.zeros_like(image)

    def pixel(value, n):
        g = min(max(-1.0 + 2.0 * value / (n - 1), -1.0), 1.0)
        return ((g + 1.0) * n - 1.0) / 2.0

    def at(k, yy, xx):
        return image[k, :, yy, xx] if 0 <= yy < h and 0 <= xx < w else torch.zeros(c,
                                                                                    dtype=image.dtype)

    for k in range(b):
        for y in range(h):
            for x in range(w):
                px = pixel(x + flow[k, 0, y, x].item(), w)
                py = pixel(y + flow[k, 1, y, x].item(), h)
                x0, y0 = math.floor(px), math.floor(py)
                ax, ay = px - x0, py - y0
                out[k, :, y, x] = ((1 - ax) * (1 - ay) * at(k, y0, x0) + ax * (1 - ay) * at(k, y0, x0 + 1)
                                   + (1 - ax) * ay * at(k, y0 + 1, x0) + ax * ay * at(k, y0 + 1, x0 + 1))
    return out


def test_clamped_grid_warp_matches_the_research_codes_sampling():
    torch.manual_seed(5)
    image = torch.rand(2, 3, 5, 7, dtype=torch.float64)
    flow = 3.0 * torch.randn(2, 2, 5, 7, dtype=torch.float64)    # many points outside
    assert torch.allclose(clamped_grid_warp(image, flow), naive_clamped_warp(image, flow),
                          atol=1e-12)
    # Zero flow does not give the frame back: the grid is stretched by W / (W - 1), and the
    # far corner is read at half a pixel beyond the centre, half of it zero.
    still = clamped_grid_warp(image, torch.zeros_like(flow))
    assert not torch.allclose(still, image)
    assert torch.allclose(still[..., -1, -1], image[..., -1, -1] / 4)


def test_clamped_grid_warp_gradient():
    torch.manual_seed(6)
    image = torch.rand(1, 2, 4, 5, dtype=torch.float64, requires_grad=True)
    flow = (0.7 * torch.randn(1, 2, 4, 5, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(clamped_grid_warp, (image, flow))


def test_network_sizes_are_checked():
    with pytest.raises(ShapeError, match="multiples of 32 and at least 64, got 48 x 64"):
        SpyNet()(torch.rand(1, 3, 48, 64), torch.rand(1, 3, 48, 64))
