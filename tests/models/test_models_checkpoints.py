"""Loading RAFT checkpoints in the key layout of the original release, and the error paths."""

from __future__ import annotations


import pytest
import torch

from weathergen.errors import FormatError
from weathergen.models import build_model, get_model, read_state_dict



def _original_layout(arch: str, prefix: str) -> tuple[dict, torch.nn.Module]:
    """A randomly initialised network's weights, keyed as the authors' files key them."""
    model = build_model(arch, iters=2)
    with torch.no_grad():  # make the batch-norm statistics non-trivial so that they matter
        for _name, buf in model.network.named_buffers():
            if buf.is_floating_point():
                buf.uniform_(0.5, 1.5)
    return {prefix + k: v.clone() for k, v in model.network.state_dict().items()}, model


@pytest.mark.parametrize("arch", ["raft", "raft-small"])
@pytest.mark.parametrize("prefix", ["module.", ""])
def test_loads_the_original_key_layout(arch, prefix, tmp_path):
    state, source = _original_layout(arch, prefix)
    path = tmp_path / "ckpt.pth"
    torch.save(state, path)
    loaded = get_model(arch, checkpoint=path, iters=2)
    for key, value in loaded.network.state_dict().items():
        assert torch.equal(value, state[prefix + key]), key
    x1, x2 = torch.rand(2, 1, 3, 64, 72).unbind(0)
    with torch.no_grad():
        assert torch.allclose(loaded(x1, x2), source(x1, x2), atol=1e-5)


def test_full_raft_has_the_published_layout_and_size():
    # Names and sizes of the released full-size checkpoints (raft-things.pth and siblings).
    state = build_model("raft").network.state_dict()
    expected_shapes = {
        "fnet.conv1.weight": (64, 3, 7, 7),
        "fnet.conv2.weight": (256, 128, 1, 1),
        "cnet.conv2.weight": (256, 128, 1, 1),
        "cnet.norm1.running_var": (64,),
        "cnet.layer2.0.norm3.running_mean": (96,),
        "cnet.layer2.0.downsample.1.running_mean": (96,),
        "update_block.encoder.convc1.weight": (256, 324, 1, 1),
        "update_block.encoder.conv.weight": (126, 256, 3, 3),
        "update_block.gru.convz1.weight": (128, 384, 1, 5),
        "update_block.gru.convq2.weight": (128, 384, 5, 1),
        "update_block.flow_head.conv1.weight": (256, 128, 3, 3),
        "update_block.mask.2.weight": (576, 256, 1, 1),
    }
    for key, shape in expected_shapes.items():
        assert tuple(state[key].shape) == shape, key
    params = sum(p.numel() for p in build_model("raft").parameters())
    assert params == 5_257_536  # the published size of RAFT


def test_released_small_checkpoint_matches_the_architecture_exactly(raft_small_weights):
    released = read_state_dict(raft_small_weights)
    ours = build_model("raft-small").network.state_dict()
    assert len(released) == 106
    assert {k[len("module."):]: tuple(v.shape) for k, v in released.items()} == {
        k: tuple(v.shape) for k, v in ours.items()}
    model = get_model("raft-small", checkpoint=raft_small_weights)
    assert sum(p.numel() for p in model.parameters()) == 990_162


def test_wrong_keys_are_listed(tmp_path):
    state, _ = _original_layout("raft-small", "module.")
    del state["module.update_block.flow_head.conv2.weight"]
    state["module.update_block.extra.weight"] = torch.zeros(3)
    path = tmp_path / "bad.pth"
    torch.save(state, path)
    with pytest.raises(FormatError) as err:
        get_model("raft-small", checkpoint=path)
    message = str(err.value)
    assert str(path) in message
    assert "missing keys (1): update_block.flow_head.conv2.weight" in message
    assert "unexpected keys (1): update_block.extra.weight" in message


def test_wrong_shapes_are_listed(tmp_path):
    # Full-RAFT weights into RAFT-small: everything mismatches; the list is shortened.
    state, _ = _original_layout("raft", "module.")
    path = tmp_path / "full.pth"
    torch.save(state, path)
    with pytest.raises(FormatError) as err:
        get_model("raft-small", checkpoint=path)
    message = str(err.value)
    assert "fnet.conv1.weight (file (64, 3, 7, 7), model (32, 3, 7, 7))" in message
    assert "shape mismatches" in message and "more" in message
    assert len(message) < 2000


def test_one_wrong_shape(tmp_path):
    state, _ = _original_layout("raft-small", "")
    state["update_block.encoder.convc1.weight"] = torch.zeros(96, 324, 1, 1)
    path = tmp_path / "shape.pth"
    torch.save(state, path)
    with pytest.raises(FormatError) as err:
        get_model("raft-small", checkpoint=path)
    assert ("shape mismatches (1): update_block.encoder.convc1.weight "
            "(file (96, 324, 1, 1), model (96, 196, 1, 1))") in str(err.value)


def test_corrupt_file_names_the_file(tmp_path):
    path = tmp_path / "corrupt.pth"
    path.write_bytes(b"\x00garbage, not a checkpoint")
    with pytest.raises(FormatError) as err:
        get_model("raft-small", checkpoint=path)
    assert str(err.value).startswith(str(path))


def test_truncated_file_names_the_file(tmp_path):
    state, _ = _original_layout("raft-small", "module.")
    path = tmp_path / "truncated.pth"
    torch.save(state, path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="truncated.pth"):
        get_model("raft-small", checkpoint=path)


def test_a_file_without_a_state_dict(tmp_path):
    path = tmp_path / "list.pth"
    torch.save([torch.zeros(1)], path)
    with pytest.raises(FormatError, match="expected a state dict"):
        get_model("raft-small", checkpoint=path)
