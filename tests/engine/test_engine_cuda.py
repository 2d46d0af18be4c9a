"""The renderer on CUDA gives the CPU's frames and gradients (run by `make gpu-check`).

Written against the CPU path and skipped where there is no CUDA device.
"""

from __future__ import annotations

import pytest
import torch

from engine_scenes import plane_pair
from weathergen.engine import BETA_ATTACK, load_preset, render_pair, sample_particles, sample_weather

pytestmark = pytest.mark.cuda

VARIABLES = ("offset1", "offset2", "color", "transparency")


def _record(name: str, pair):
    if name == "snow-light":          # the weather-field model, far limited to the small scene
        return sample_weather(pair, load_preset(name, {"far": 5.0}), seed=3, frame_rate=24.0)
    return sample_particles(pair, load_preset(name, {"count": 6 if name == "fog" else 200}), seed=3)


@pytest.mark.parametrize("name", ["snow", "rain", "sparks", "fog", "snow-light"])
def test_render_on_cuda_matches_the_cpu(name):
    pair = plane_pair(48, 64, depth=2.5, near_block=True)
    parts = _record(name, pair)
    assert parts.count > 0
    cpu = render_pair(pair, parts)
    gpu = render_pair(pair, parts, device="cuda")
    for key in ("image1", "image2", "opacity1", "opacity2"):
        got = getattr(gpu, key)
        assert got.device.type == "cuda"
        assert float((got.cpu() - getattr(cpu, key)).abs().max()) <= 1 / 255, key


@pytest.mark.parametrize("name", ["snow", "rain"])
def test_gradients_on_cuda_match_the_cpu(name):
    pair = plane_pair(48, 64, depth=2.5, near_block=True)
    parts = _record(name, pair)
    grads = {}
    for device in ("cpu", "cuda"):
        leaves = {k: getattr(parts, k).clone().to(device).requires_grad_(True) for k in VARIABLES}
        out = render_pair(pair, parts.to(device).replace(**leaves), beta=BETA_ATTACK, device=device)
        (out.image1.square().sum() + out.image2.sum()).backward()
        grads[device] = {k: v.grad.cpu() for k, v in leaves.items()}
    for k in VARIABLES:
        cpu, gpu = grads["cpu"][k], grads["cuda"][k]
        assert torch.isfinite(gpu).all(), k
        scale = float(cpu.abs().max()) or 1.0
        assert float((gpu - cpu).abs().max()) <= 1e-3 * scale, k


def test_combined_weather_on_cuda_matches_the_cpu():
    """Snow, fog and a weather field in one pass: frames and the gradient of every layer."""
    pair = plane_pair(48, 64, depth=2.5, near_block=True)
    preset = load_preset("snow+fog+snow-light", {"snow.count": 150, "fog.count": 4,
                                                 "snow-light.far": 5.0})
    layers = sample_weather(pair, preset, seed=3, frame_rate=24.0)
    assert all(r.count for r in layers.layers)
    results = {}
    for device in ("cpu", "cuda"):
        leaves = [r.to(device).replace(color=r.color.clone().to(device).requires_grad_(True))
                  for r in layers.layers]
        out = render_pair(pair, type(layers)(tuple(leaves), layers.names), beta=BETA_ATTACK,
                          device=device)
        (out.image1.square().sum() + out.image2.sum()).backward()
        results[device] = (out, [r.color.grad.cpu() for r in leaves])
    (cpu, cpu_grads), (gpu, gpu_grads) = results["cpu"], results["cuda"]
    for key in ("image1", "image2", "opacity1", "opacity2"):
        assert float((getattr(gpu, key).detach().cpu() - getattr(cpu, key).detach()).abs().max()) \
            <= 1 / 255, key
    for a, b in zip(cpu_grads, gpu_grads):
        assert torch.allclose(a, b, rtol=1e-3, atol=1e-3)
        assert float(a.abs().max()) > 0
