"""``--precision``: the choices each network accepts or refuses, the parts that stay float32 under
autocast, and each network's flow against float32 within its documented bound (tiny frames,
random weights, on the CPU: bf16 and fp16 autocast both run there)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from weathergen.errors import ConfigError
from weathergen.models import (AUTOCAST, PRECISIONS, available_models, build_model, get_model,
                               model_spec, resolve_precision)
from weathergen.models import flowformer, flownet2, flownet_parts, gma, raft, registry, spynet
from weathergen.models.base import in_float32


@pytest.mark.parametrize("name", available_models())
def test_each_network_accepts_its_precisions_and_refuses_the_others(name):
    spec = model_spec(name)
    for precision in PRECISIONS:
        if precision in spec.refused_precisions:
            with pytest.raises(ConfigError, match=f"^precision {precision} is refused for "
                                                  f"'{name}'") as refused:
                resolve_precision(name, precision, None, "cuda")
            assert "\n" not in str(refused.value) and "bound" in str(refused.value)
        else:
            assert resolve_precision(name, precision, None, "cuda") == precision
    with pytest.raises(ConfigError, match="^precision tf32 needs a CUDA device"):
        resolve_precision(name, "tf32", None, "cpu")
    # without --precision: --amp's answer (the paper's configuration), fp16 where it is on
    assert resolve_precision(name, None, None, "cpu") == "float32"
    assert resolve_precision(name, None, None, "cuda") == ("fp16" if spec.amp else "float32")


def test_a_precision_beyond_a_networks_bound_is_refused_in_one_line(monkeypatch):
    strict = dataclasses.replace(model_spec("spynet"), refused_precisions=("fp16",),
                                 precision_bound=0.02)
    monkeypatch.setitem(registry._ARCHITECTURES, "spynet", strict)
    with pytest.raises(ConfigError) as refused:
        resolve_precision("spynet", "fp16", None, "cpu")
    message = refused.value.render(lambda name: f"--{name}")
    assert message == ("--precision fp16 is refused for 'spynet': its flow differs from "
                       "float32's by more than its bound, 0.02 px RMS (docs/models.md)")
    assert resolve_precision("spynet", "bf16", None, "cpu") == "bf16"
    with pytest.raises(ConfigError, match="refused"):
        get_model("spynet", checkpoint="unused", precision="fp16")


def test_precision_and_amp_are_exclusive_and_checked():
    with pytest.raises(ConfigError, match="^precision and amp are exclusive"):
        resolve_precision("raft", "bf16", True, "cuda")
    with pytest.raises(ConfigError, match="^precision must be one of float32, tf32, bf16, fp16"):
        resolve_precision("raft", "half", None, "cpu")
    assert resolve_precision("gma", None, False, "cuda") == "float32"
    assert resolve_precision("raft", None, True, "cuda") == "fp16"


def test_the_amp_switch_is_fp16_autocast():
    model = build_model("raft-small", iters=1)
    model.amp = True
    assert model.precision == "fp16" and model.amp
    model.precision = "bf16"
    assert model.amp
    model.amp = False
    assert model.precision == "float32" and not model.amp


#: Per network, the parts that stay float32 under autocast (docs/models.md): where they live.
FLOAT32_PARTS = {
    "raft": [(raft.CorrelationPyramid, "lookup")],
    "raft-small": [(raft.CorrelationPyramid, "lookup")],
    "gma": [(raft.CorrelationPyramid, "lookup"), (gma, "_softmax_attention")],
    "flowformer": [(flowformer, "cost_volume"), (flowformer, "cost_window")],
    "flownetc": [(flownet_parts, "correlation")],
    "flownetcrobust": [(flownet_parts, "correlation")],
    "flownet2": [(flownet_parts, "correlation"), (flownet2, "warp")],
    "spynet": [(spynet, "clamped_grid_warp")],
    "spynet-sniklaus": [(spynet, "border_warp")],
}
SIZES = {"flowformer": (64, 64), "spynet": (64, 64), "spynet-sniklaus": (64, 64)}


def test_every_network_has_its_float32_parts_listed():
    assert set(FLOAT32_PARTS) == set(available_models())


def tiny_frames(name: str):
    torch.manual_seed(1)
    h, w = SIZES.get(name, (64, 64))
    return torch.rand(2, 1, 3, h, w).unbind(0)


@pytest.mark.parametrize("name", sorted(FLOAT32_PARTS))
def test_autocast_leaves_the_stated_parts_float32(name, monkeypatch):
    torch.manual_seed(0)
    model = build_model(name, iters=1)
    seen: dict = {}
    for owner, attribute in FLOAT32_PARTS[name]:
        original = getattr(owner, attribute)

        def recording(*args, _original=original, _key=attribute, **kwargs):
            out = _original(*args, **kwargs)
            seen.setdefault(_key, set()).add(out.dtype)
            return out

        monkeypatch.setattr(owner, attribute, recording)
    convs = [m for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    convs[0].register_forward_hook(lambda m, i, o: seen.setdefault("conv", set()).add(o.dtype))
    model.precision = "bf16"
    x1, x2 = tiny_frames(name)
    with torch.no_grad():
        flow = model(x1, x2)
    assert seen.pop("conv") == {torch.bfloat16}       # autocast is on around them
    assert seen == {attribute: {torch.float32} for _, attribute in FLOAT32_PARTS[name]}
    assert flow.dtype == torch.float32                 # the loss is computed in float32


def test_float32_parts_keep_float64_for_gradient_checks():
    double = in_float32(lambda a, b: a * b)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert double(torch.ones(2, dtype=torch.float64), 2.0).dtype == torch.float64
        assert double(torch.ones(2, dtype=torch.bfloat16), 2.0).dtype == torch.float32


#: Networks whose reduced-precision convolutions are slow on a CPU (no bfloat16/float16 units).
SLOW_ON_CPU = ("flownet2", "spynet", "spynet-sniklaus")


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW_ON_CPU
                                  else n for n in available_models()])
def test_the_flow_in_each_accepted_precision_is_within_the_networks_bound(name):
    spec = model_spec(name)
    torch.manual_seed(0)
    model = build_model(name, iters=2)
    x1, x2 = tiny_frames(name)
    with torch.no_grad():
        reference = model(x1, x2)
        for precision in AUTOCAST:
            if precision in spec.refused_precisions:
                continue
            model.precision = precision
            flow = model(x1, x2)
            rms = (flow - reference).norm(dim=1).pow(2).mean().sqrt().item()
            assert torch.isfinite(flow).all() and 0 < rms <= spec.precision_bound, (precision, rms)
