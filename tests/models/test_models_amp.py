"""Mixed precision (``--amp``): the default per network follows the paper's configurations (GMA's
ran under CUDA autocast, the others in float32), --amp is refused on the CPU, requests that cannot be
met fail with one line naming the option; on CUDA (skipped without one) the authors' autocast
regions run in float16 and the flow stays close to the float32 one."""

from __future__ import annotations

import pytest
import torch

from weathergen.errors import ConfigError
from weathergen.models import available_models, build_model, get_model, model_spec, resolve_amp

#: The paper's configurations: GMA with "mixed_precision": true, every other network float32.
PAPER_AMP = {"gma": True}


@pytest.mark.parametrize("name", available_models())
def test_default_follows_the_papers_configuration_on_cuda_and_is_off_elsewhere(name):
    assert resolve_amp(name, None, "cuda") is PAPER_AMP.get(name, False)
    assert resolve_amp(name, None, "cuda:1") is PAPER_AMP.get(name, False)
    assert resolve_amp(name, None, "cpu") is False
    assert resolve_amp(name, False, "cuda") is False


def test_a_checkpoint_name_resolves_as_its_network():
    assert resolve_amp("gma-things", None, "cuda") is True
    assert resolve_amp("raft-kitti", None, "cuda") is False


@pytest.mark.parametrize("name", available_models())
def test_registration_and_adapter_agree_on_the_mode(name):
    spec = model_spec(name)
    assert spec.mixed_precision == build_model(name).supports_amp
    if spec.mixed_precision:
        assert resolve_amp(name, True, "cuda") is True
    else:
        with pytest.raises(ConfigError) as err:
            resolve_amp(name, True, "cuda")
        message = err.value.render(lambda n: f"--{n}")
        assert message.startswith(f"--amp: '{name}' has no mixed-precision mode")
        assert "gma, raft, raft-small" in message


@pytest.mark.parametrize("device", ["cpu", None])
def test_asking_for_it_on_the_cpu_is_an_error_naming_the_option(device):
    with pytest.raises(ConfigError) as err:
        resolve_amp("gma", True, device)
    message = err.value.render(lambda n: f"--{n}")
    assert message.startswith("--amp needs a CUDA device") and "\n" not in message


def test_get_model_sets_the_adapter_and_refuses_networks_without_the_mode(tmp_path):
    path = tmp_path / "small.pth"
    torch.save(build_model("raft-small").network.state_dict(), path)
    assert get_model("raft-small", checkpoint=path, amp=True).amp is True
    assert get_model("raft-small", checkpoint=path).amp is False
    with pytest.raises(ConfigError, match="no mixed-precision mode"):
        get_model("spynet", checkpoint=path, amp=True)


@pytest.mark.parametrize("name", ["raft-small", "gma"])
def test_on_cpu_tensors_the_mode_is_cpu_autocast_of_the_same_regions(name):
    """The mode is autocast on the frames' device (``--amp`` itself stays CUDA-only): on the CPU
    the authors' regions run in float16 and the flow stays float32."""
    torch.manual_seed(0)
    model = build_model(name, iters=2)
    seen = []
    model.network.fnet.register_forward_hook(lambda m, i, o: seen.append(o.dtype))
    x1, x2 = torch.rand(2, 1, 3, 64, 64).unbind(0)
    with torch.no_grad():
        plain = model(x1, x2)
        model.amp = True
        mixed = model(x1, x2)
    assert seen == [torch.float32, torch.float16]
    assert mixed.dtype == torch.float32 and not torch.equal(plain, mixed)
    assert (mixed - plain).abs().max().item() <= 2e-2 * plain.abs().max().item() + 1e-3


@pytest.mark.cuda
@pytest.mark.parametrize("name", ["raft", "raft-small", "gma"])
def test_on_cuda_the_authors_regions_run_in_float16(name):
    torch.manual_seed(0)
    model = build_model(name, iters=3).cuda()
    seen = {}

    def record(key, output_dtype):
        def hook(module, inputs, output):      # returns None: the output stays as it is
            seen.setdefault(key, output_dtype(output))
        return hook

    model.network.fnet.register_forward_hook(record("fnet", lambda o: o.dtype))
    model.network.update_block.register_forward_hook(record("update", lambda o: o[1].dtype))
    x1 = torch.rand(1, 3, 96, 128, device="cuda", requires_grad=True)
    x2 = torch.rand(1, 3, 96, 128, device="cuda", requires_grad=True)
    with torch.no_grad():
        plain = model(x1, x2)
    assert not seen or seen == {"fnet": torch.float32, "update": torch.float32}
    seen.clear()
    model.amp = True
    mixed = model(x1, x2)
    assert seen == {"fnet": torch.float16, "update": torch.float16}
    assert mixed.dtype == torch.float32 and torch.isfinite(mixed).all()
    scale = plain.abs().max().item()
    assert (mixed.detach() - plain).abs().max().item() <= 2e-2 * scale + 1e-3
    mixed.square().mean().backward()
    for image in (x1, x2):
        assert torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0
