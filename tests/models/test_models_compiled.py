"""compile_iterations: the modules every refinement iteration runs, compiled in place.

Inductor's code generation takes minutes on a small CPU, so the wiring is checked with the
``aot_eager`` backend (traced graphs, eager kernels): the same modules are wrapped, the state
dict keeps its keys, and flow and input gradients equal the eager network's. The GPU check
measures Inductor's own kernels (``benchmarks/bench_tables.py --compile``)."""

from __future__ import annotations

import pytest
import torch
from numerics import assert_float32_close, rounding_k

from weathergen.errors import ConfigError
from weathergen.models import build_model, compile_iterations
from weathergen.models.compiled import iteration_modules


def _flow_and_grad(model, a, b):
    x = a.clone().requires_grad_(True)
    flow = model(x, b)
    flow.square().mean().backward()
    return flow.detach(), x.grad


def test_compiled_iterations_give_the_eager_flow_and_gradient():
    torch.manual_seed(0)
    model = build_model("raft-small", iters=2)
    model.requires_grad_(False)
    keys = list(model.state_dict())
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(1, 3, 64, 96, generator=g), torch.rand(1, 3, 64, 96, generator=g)
    flow, grad = _flow_and_grad(model, a, b)
    assert compile_iterations(model, backend="aot_eager") == ["network.update_block"]
    assert list(model.state_dict()) == keys
    flow_c, grad_c = _flow_and_grad(model, a, b)
    # Equal up to float32 rounding (the traced graph may add in another order), relative to
    # the values' size (tests/numerics.py): RAFT-small's chain of sums, forward, is its
    # encoder's 20 convolutions, the correlation, about 10 per step and the upsampling, the
    # longest under 256 x 3 x 3 terms; the gradient goes the same way back.
    sums = 20 + 1 + 10 * 2 + 1
    assert_float32_close(flow_c, flow, rounding_k(sums, 256 * 9), "flow")
    assert_float32_close(grad_c, grad, rounding_k(2 * sums, 256 * 9), "input gradient")


def test_flowformer_compiles_its_decoder_iteration_and_networks_without_iterations_nothing():
    model = build_model("flowformer", iters=1)
    names = [n for n, _ in iteration_modules(model)]
    assert names == ["network.memory_decoder.flow_token_encoder",
                     "network.memory_decoder.decoder_layer",
                     "network.memory_decoder.update_block"]
    assert compile_iterations(build_model("spynet"), backend="aot_eager") == []
    with pytest.raises(ConfigError, match="compile mode 'fast'"):
        compile_iterations(model, "fast")
