"""Set-up and checks shared by the flow-network tests: random-weight networks saved as the
authors' files, random input pairs, input gradients, a served download and the two commands
(attack, then evaluate) on a tiny Sintel-format pair."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner
from conftest import write_fake_sintel

from weathergen.errors import FormatError
from weathergen.models import build_model, get_model


# -- random-weight networks and their files ------------------------------------------------------

def random_release(arch: str, prefix: str = "module.", *, seed: int | None = None,
                   gamma: float = 0.7, iters: int = 2) -> tuple[dict, torch.nn.Module]:
    """A network ``arch`` with random weights, and its state dict as the authors' file holds it
    (every key behind ``prefix``, e.g. DataParallel's ``module.``). Floating-point buffers
    (batch-norm statistics) are drawn in [0.5, 1.5] and a motion aggregation weight (GMA's
    ``gamma``) is set to ``gamma``, so that both matter to the flow. ``seed``: seeds torch's
    global generator first."""
    if seed is not None:
        torch.manual_seed(seed)
    model = build_model(arch, iters=iters)
    with torch.no_grad():
        for _, buf in model.network.named_buffers():
            if buf.is_floating_point():
                buf.uniform_(0.5, 1.5)
        for name, param in model.network.named_parameters():
            if name.endswith("aggregator.gamma"):
                param.fill_(gamma)
    return {prefix + k: v.clone() for k, v in model.network.state_dict().items()}, model


def saved(state: dict, path: Path) -> Path:
    """``state`` written with :func:`torch.save` at ``path``."""
    torch.save(state, path)
    return path


def assert_loads_strictly(arch: str, path: Path, state: dict, source: torch.nn.Module,
                          prefix: str, size: tuple[int, int]) -> None:
    """The file ``path`` (``state``, keys behind ``prefix``) loads into ``arch`` value for value,
    and the loaded network gives ``source``'s flow on a random pair of ``size``."""
    loaded = get_model(arch, checkpoint=path, iters=2)
    for key, value in loaded.network.state_dict().items():
        assert torch.equal(value, state[prefix + key]), key
    x1, x2 = random_frames(1, size)
    with torch.no_grad():
        assert torch.allclose(loaded(x1, x2), source(x1, x2), atol=1e-5)


def load_error(arch: str, state: dict, path: Path) -> str:
    """The message of the :class:`FormatError` that loading ``state`` (saved at ``path``) into
    ``arch`` raises; it starts with the file's name."""
    torch.save(state, path)
    with pytest.raises(FormatError) as err:
        get_model(arch, checkpoint=path)
    message = str(err.value)
    assert message.startswith(str(path))
    return message


# -- the contract ------------------------------------------------------------------------------

def assert_flow_at_input_size(model, size: tuple[int, int], batch: int = 1) -> None:
    """The flow of a random batch of ``size`` comes back at that size, finite."""
    x1, x2 = torch.rand(2, batch, 3, *size).unbind(0)
    with torch.no_grad():
        flow = model(x1, x2)
    assert flow.shape == (batch, 2, *size) and torch.isfinite(flow).all()


def assert_gradient_reaches_both_images(model, size: tuple[int, int]) -> torch.Tensor:
    """A loss on the flow of a random pair of ``size`` has a finite, non-zero gradient in both
    images; returns the flow."""
    x1 = torch.rand(1, 3, *size, requires_grad=True)
    x2 = torch.rand(1, 3, *size, requires_grad=True)
    flow = model(x1, x2)
    flow.square().mean().backward()
    for grad in (x1.grad, x2.grad):
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0
    return flow


def input_gradient(model, x1: torch.Tensor, x2: torch.Tensor) -> torch.Tensor:
    """The gradient of the flow's sum in both images, flattened into one vector."""
    a, b = x1.clone().requires_grad_(), x2.clone().requires_grad_()
    model(a, b).sum().backward()
    return torch.cat([a.grad.flatten(), b.grad.flatten()])


def random_frames(batch: int, size: tuple[int, int], seed: int = 0):
    """Two random frame batches ``(batch, 3, *size)`` in [0, 1), drawn from ``seed`` with a
    generator of their own (whatever the global generator's state)."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(2, batch, 3, *size, generator=g).unbind(0)


def batch_and_alone(model, size: tuple[int, int], index: int = 0, seed: int = 0):
    """The flow of pair ``index`` of a random batch of two pairs of ``size`` (drawn from
    ``seed``), and the flow of that pair alone: equal up to rounding when the batch elements
    are independent."""
    x1, x2 = random_frames(2, size, seed)
    one = slice(index, index + 1)
    with torch.no_grad():
        both = model(x1, x2)
        alone = model(x1[one], x2[one])
    return both[one], alone


# -- a served download ---------------------------------------------------------------------------

def serve(monkeypatch, payload) -> list:
    """Make ``urllib.request.urlopen`` answer every address with ``payload`` (no network), or,
    for a dict, each address with ``payload[address]`` (others fail as unreachable); returns the
    list the requested addresses are appended to."""
    import urllib.request

    requested = []

    class Response(io.BytesIO):
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    def urlopen(url, timeout):
        requested.append(url)
        if isinstance(payload, dict):
            if url not in payload:
                raise OSError(f"no such address: {url}")
            return Response(payload[url])
        return Response(payload)

    monkeypatch.setattr(urllib.request, "urlopen", urlopen)
    return requested


# -- the command line ----------------------------------------------------------------------------

def invoke(args):
    from weathergen.cli.main import _register, cli

    _register()
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def tiny_sintel(folder: Path) -> list:
    """One 40x56 Sintel-format frame pair (an odd size for every network's padding multiple)
    written below ``folder``, and the options that select it."""
    root = write_fake_sintel(folder, scenes=("alley",), frames=2, size=(40, 56))
    return ["--dataset", "sintel", "--root", root, "--scenes", "alley", "--frames-per-scene", "1"]


def attack_then_evaluate(model_options: list, data_options: list, tmp_path: Path):
    """``weathergen attack`` (one step, 40 snow particles) with ``model_options`` on the pairs of
    ``data_options``, then ``weathergen evaluate`` of its output with the same network; both must
    succeed. Returns the attack's summary.json, its manifest.json and evaluate's JSON."""
    out = tmp_path / "snow"
    attacked = invoke(["attack", *model_options, *data_options, "--steps", "1", "--set",
                       "count=40", "--seed", "1", "--out", out, "--quiet"])
    assert attacked.exit_code == 0, attacked.output
    evaluated = invoke(["evaluate", "--weather", out, *model_options, "--json",
                        tmp_path / "eval.json"])
    assert evaluated.exit_code == 0, evaluated.output
    return tuple(json.loads(path.read_text()) for path in
                 (out / "summary.json", out / "manifest.json", tmp_path / "eval.json"))
