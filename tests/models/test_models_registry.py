"""The flow-model registry: names, checkpoint resolution and its error messages."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from model_checks import serve

from weathergen.errors import ConfigError
from weathergen.models import (FlowModel, available_checkpoints, available_models, build_model,
                               cache_dir, get_model)


def _save_random(arch: str, path: Path, prefix: str = "module.") -> Path:
    state = build_model(arch).network.state_dict()
    torch.save({prefix + k: v for k, v in state.items()}, path)
    return path


def test_known_names():
    assert {"raft", "raft-small"} <= set(available_models())
    assert {"raft-things", "raft-sintel", "raft-kitti", "raft-chairs", "raft-small"} <= set(
        available_checkpoints())
    assert set(available_checkpoints("raft")) == {"raft-chairs", "raft-things", "raft-sintel",
                                                  "raft-kitti"}


@pytest.mark.parametrize("arch", available_models())
def test_every_registered_model_builds_into_the_contract(arch):
    model = build_model(arch, iters=1)
    assert isinstance(model, FlowModel)
    assert model.architecture == arch
    assert not model.training
    x = torch.rand(1, 3, 64, 64)
    assert model(x, x).shape == (1, 2, 64, 64)


def test_unknown_model_lists_the_known_ones():
    with pytest.raises(ConfigError) as err:
        get_model("flownet-9000")
    message = str(err.value)
    assert "flownet-9000" in message
    for name in available_models() + available_checkpoints():
        assert name in message


def test_missing_named_checkpoint_says_which_file_to_put_where(tmp_path, monkeypatch):
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path / "cache"))
    with pytest.raises(ConfigError) as err:
        get_model("raft", checkpoint="raft-things")
    message = str(err.value)
    expected = tmp_path / "cache" / "models" / "raft-things.pth"
    assert str(expected) in message
    assert "models/raft-things.pth" in message  # where it is inside the release archive
    assert "\n" not in message


def test_default_checkpoint_of_raft_is_the_sintel_one(tmp_path, monkeypatch):
    # The paper attacks the Sintel-trained models.
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    with pytest.raises(ConfigError, match="raft-sintel.pth"):
        get_model("raft")


def test_named_checkpoint_is_found_in_the_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    assert cache_dir() == tmp_path / "models"
    cache_dir().mkdir(parents=True)
    _save_random("raft-small", cache_dir() / "raft-small.pth")
    model = get_model("raft-small", iters=2)
    assert model.iters == 2
    assert all(not p.requires_grad for p in model.parameters())


def test_a_checkpoint_name_selects_its_architecture(tmp_path, monkeypatch):
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    cache_dir().mkdir(parents=True)
    _save_random("raft", cache_dir() / "raft-kitti.pth")
    assert get_model("raft-kitti").architecture == "raft"


def test_checkpoint_of_another_architecture_is_refused():
    with pytest.raises(ConfigError, match="'raft-things' is for 'raft', not 'raft-small'"):
        get_model("raft-small", checkpoint="raft-things")


def test_missing_checkpoint_path(tmp_path):
    missing = tmp_path / "nope.pth"
    with pytest.raises(ConfigError, match="nope.pth"):
        get_model("raft-small", checkpoint=missing)


@pytest.mark.parametrize("iters", [0, -3, 2.5, True])
def test_bad_iteration_counts(iters):
    with pytest.raises(ConfigError, match="iters"):
        build_model("raft-small", iters=iters)


def test_bad_device(tmp_path):
    ckpt = _save_random("raft-small", tmp_path / "small.pth")
    with pytest.raises(ConfigError, match="device"):
        get_model("raft-small", checkpoint=ckpt, device="warp-drive")


def test_download_refused_without_network_says_where_to_put_the_file(tmp_path, monkeypatch):
    import urllib.request

    def no_network(*args, **kwargs):
        raise OSError("network is unreachable")

    monkeypatch.setattr(urllib.request, "urlopen", no_network)
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    with pytest.raises(ConfigError) as err:
        get_model("raft-things", download=True)
    assert str(tmp_path / "models" / "raft-things.pth") in str(err.value)
    assert not list((tmp_path / "models").glob("*.pth")), "no partial file may be left behind"


def test_download_extracts_the_member_atomically(tmp_path, monkeypatch):
    """A fake release archive served from disk: the checkpoint lands in the cache and loads."""
    import io
    import zipfile

    buf = io.BytesIO()
    state = build_model("raft-small").network.state_dict()
    member = io.BytesIO()
    torch.save({"module." + k: v for k, v in state.items()}, member)
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("models/raft-small.pth", member.getvalue())
    archive = buf.getvalue()

    serve(monkeypatch, archive)
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    from weathergen.models import checkpoint_spec, download_checkpoint
    from dataclasses import replace

    spec = replace(checkpoint_spec("raft-small"), sha256=None)  # the fake file differs
    path = download_checkpoint(spec)
    assert path == tmp_path / "models" / "raft-small.pth"
    assert sorted(p.name for p in path.parent.iterdir()) == ["raft-small.pth"]
    assert get_model("raft-small", checkpoint=path) is not None


def test_download_with_a_wrong_checksum_leaves_nothing_behind(tmp_path, monkeypatch):
    import io
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("models/raft-small.pth", b"not the released file")

    serve(monkeypatch, buf.getvalue())
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    from weathergen.models import checkpoint_spec, download_checkpoint

    with pytest.raises(ConfigError, match="sha256"):
        download_checkpoint(checkpoint_spec("raft-small"))
    assert list((tmp_path / "models").iterdir()) == []


def test_raft_small_by_name_is_the_released_file_shipped_with_the_package(tmp_path, monkeypatch):
    """With an empty cache and no network, the name finds the weights installed with the package:
    the released file itself (its published checksum), beside its licence."""
    import urllib.request

    from weathergen.models import checkpoint_spec
    from weathergen.models.checkpoints import resolve_named, sha256_of

    def no_network(*args, **kwargs):
        raise AssertionError("a shipped checkpoint must not be downloaded")

    monkeypatch.setattr(urllib.request, "urlopen", no_network)
    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    spec = checkpoint_spec("raft-small")
    path = resolve_named(spec, download=True)
    assert path.parent.name == "weights" and path.parent.parent.name == "models"
    assert sha256_of(path) == spec.sha256
    assert (path.parent / "raft-small.LICENSE").read_text().startswith("BSD 3-Clause")
    model = get_model("raft-small", iters=2)                  # the default checkpoint: the same file
    assert not (tmp_path / "models").exists()                 # nothing fetched or copied
    assert model(torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64)).shape == (1, 2, 64, 64)


def test_a_cached_file_of_the_name_takes_precedence_over_the_shipped_one(tmp_path, monkeypatch):
    from weathergen.models import checkpoint_spec
    from weathergen.models.checkpoints import resolve_named

    monkeypatch.setenv("WEATHERGEN_CACHE", str(tmp_path))
    cache_dir().mkdir(parents=True)
    mine = _save_random("raft-small", cache_dir() / "raft-small.pth")
    assert resolve_named(checkpoint_spec("raft-small")) == mine
