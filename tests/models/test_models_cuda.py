"""Every flow network on CUDA gives the CPU's flow and input gradients (run by `make gpu-check`).

Random weights; TF32 is switched off for the comparison, so that both devices compute in float32.
Skipped where there is no CUDA device.
"""

from __future__ import annotations

import pytest
import torch

from weathergen.models import available_models, build_model

pytestmark = pytest.mark.cuda


@pytest.fixture
def full_float32():
    before = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = before


@pytest.mark.parametrize("arch", available_models())
def test_network_on_cuda_matches_the_cpu(arch, full_float32):
    torch.manual_seed(0)
    model = build_model(arch, iters=3)
    g = torch.Generator().manual_seed(1)
    x1, x2 = torch.rand(1, 3, 64, 128, generator=g), torch.rand(1, 3, 64, 128, generator=g)
    results = {}
    for device in ("cpu", "cuda"):
        model.to(device)
        a, b = (x.to(device).detach().requires_grad_(True) for x in (x1, x2))   # leaves on each device
        flow = model(a, b)
        flow.square().mean().backward()
        results[device] = (flow.detach().cpu(), a.grad.cpu())
    (flow_cpu, grad_cpu), (flow_gpu, grad_gpu) = results["cpu"], results["cuda"]
    assert flow_gpu.shape == (1, 2, 64, 128) and torch.isfinite(flow_gpu).all()
    assert float((flow_gpu - flow_cpu).abs().max()) <= 1e-3 * (1 + float(flow_cpu.abs().max()))
    scale = float(grad_cpu.abs().max()) or 1.0
    assert float((grad_gpu - grad_cpu).abs().max()) <= 1e-2 * scale
