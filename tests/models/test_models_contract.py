"""A network resolved once and its contract checked: the user's file read once per run, the input
convention a plain module declares (attribute, decorator, --model-input) given to it, the note for
one that declares none, and the refusals before anything is written (a flow that is not finite,
of another shape, or without a gradient to the frames, for an attack)."""

from __future__ import annotations

import builtins
import io
import json
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from model_checks import invoke, tiny_sintel

from weathergen.errors import ConfigError, ShapeError
from weathergen.models import ModuleFlowModel, get_model, resolve_network

NETWORKS = textwrap.dedent('''
    import torch
    from torch import nn
    from weathergen.models import flow_input

    SEEN = []          # the first frame of every call, as the module received it

    class Record(nn.Module):
        def __init__(self):
            super().__init__()
            self.scale = nn.Parameter(torch.tensor(0.5))

        def forward(self, image1, image2):
            SEEN.append(image1.detach().clone())
            return self.scale * (image1[:, :2] - image2[:, 1:])

    def plain():
        return Record()

    @flow_input(255, "BGR")
    def decorated():
        return Record()

    class Declared(Record):
        input_range = (0, 255)
        channel_order = "bgr"

    class Wrong(Record):
        input_range = 100

    class NaNs(Record):
        def forward(self, image1, image2):
            return super().forward(image1, image2) * float("nan")

    class NoGrad(Record):
        def forward(self, image1, image2):
            with torch.no_grad():
                return super().forward(image1, image2)

    class Half(Record):
        def forward(self, image1, image2):
            return super().forward(image1, image2)[..., ::2, :]
''')


@pytest.fixture(scope="module")
def nets(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("contract") / "contract_nets.py"
    path.write_text(NETWORKS)
    return path


@pytest.fixture(scope="module")
def sintel_options(tmp_path_factory):
    return tiny_sintel(tmp_path_factory.mktemp("sintel"))


def seen_by(model, x1, x2) -> torch.Tensor:
    """The first frame as the module behind ``model`` received it."""
    module = sys.modules[type(model.network).__module__]
    module.SEEN.clear()
    with torch.no_grad():
        model(x1, x2)
    return module.SEEN[-1]


@pytest.mark.parametrize("name, model_input", [("decorated", None), ("Declared", None),
                                               ("plain", "bgr255")])
def test_a_declared_0_255_bgr_network_receives_converted_frames(nets, name, model_input):
    network = resolve_network(f"{nets}:{name}", model_input)
    assert network.input == "bgr255" and network.declared and network.note() is None
    assert network.source()["input"] == "bgr255"
    model = get_model(network)
    x1, x2 = torch.rand(2, 1, 3, 8, 8, generator=torch.Generator().manual_seed(1)).unbind(0)
    got = seen_by(model, x1, x2)
    for channel in range(3):      # B, G, R of our R, G, B, times 255
        assert torch.allclose(got[0, channel], 255 * x1[0, 2 - channel], atol=1e-4)


def test_an_undeclared_plain_module_gets_rgb_0_1_and_a_note(nets):
    network = resolve_network(f"{nets}:plain")
    assert network.input == "rgb" and not network.declared
    assert "declares no input convention: its frames are given as RGB in [0, 1]" in network.note()
    x1, x2 = torch.rand(2, 1, 3, 8, 8).unbind(0)
    assert torch.equal(seen_by(get_model(network), x1, x2), x1)
    # the registered networks and a FlowModel of your own normalise themselves: no note
    assert resolve_network("raft-small").note() is None


def test_a_bad_or_conflicting_convention_is_refused(nets):
    with pytest.raises(ConfigError, match="input_range must be 1 or 255"):
        resolve_network(f"{nets}:Wrong")
    with pytest.raises(ConfigError, match="model_input rgb: .* declares bgr255"):
        resolve_network(f"{nets}:decorated", "rgb")
    with pytest.raises(ConfigError, match="applies to a plain module"):
        resolve_network("raft-small", "bgr")


def test_non_finite_and_wrong_shape_are_refused_when_loaded(nets):
    with pytest.raises(ConfigError, match="not finite"):
        get_model(f"{nets}:NaNs")
    with pytest.raises(ShapeError, match="returned a flow of shape"):
        get_model(f"{nets}:Half")
    assert isinstance(get_model(f"{nets}:NoGrad"), ModuleFlowModel)    # evaluating needs none


def cli_lines(result) -> tuple[list, list]:
    """(notes, other lines) of a command's output."""
    lines = result.output.strip().splitlines()
    return [t for t in lines if t.startswith("Note:")], [t for t in lines if not t.startswith("Note:")]


@pytest.mark.parametrize("name, words", [("NaNs", "not finite"), ("Half", "returned a flow of shape"),
                                         ("NoGrad", "gives no gradient to its input frames")])
def test_attack_refuses_a_broken_network_in_one_line_before_writing(nets, sintel_options, tmp_path,
                                                                   name, words):
    result = invoke(["attack", "--model", f"{nets}:{name}", *sintel_options, "--steps", "1",
                     "--set", "count=20", "--out", tmp_path / "o", "--quiet"])
    _, lines = cli_lines(result)
    assert result.exit_code == 2 and len(lines) == 1 and words in lines[0], result.output
    assert not (tmp_path / "o").exists()


def test_benchmark_refuses_a_network_without_gradient_before_any_run(nets, sintel_options, tmp_path):
    result = invoke(["benchmark", "--networks", f"{nets}:NoGrad", "--presets", "snow", "--lp", "",
                     "--steps", "1", *sintel_options, "--out", tmp_path / "b", "--quiet"])
    _, lines = cli_lines(result)
    assert result.exit_code == 2 and len(lines) == 1 and "no gradient" in lines[0], result.output
    assert not (tmp_path / "b").exists()


class FileReads:
    """Counts the times one file is opened, through every way Python opens files."""

    def __init__(self, path: Path, monkeypatch):
        self.path, self.count = path.resolve(), 0
        for owner, name in ((builtins, "open"), (io, "open"), (io, "open_code")):
            monkeypatch.setattr(owner, name, self.spy(getattr(owner, name)))

    def spy(self, opener):
        def opened(file, *args, **kwargs):
            if isinstance(file, (str, Path)) and Path(file).resolve() == self.path:
                self.count += 1
            return opener(file, *args, **kwargs)
        return opened


def test_the_users_file_is_read_once_per_run(nets, sintel_options, tmp_path, monkeypatch):
    net = tmp_path / "once.py"
    net.write_text(NETWORKS.replace("0.5", "0.25"))     # a file no other test has run
    reads = FileReads(net, monkeypatch)
    out = tmp_path / "a"
    attacked = invoke(["attack", "--model", f"{net}:decorated", *sintel_options, "--steps", "2",
                       "--set", "count=20", "--out", out, "--quiet"])
    assert attacked.exit_code == 0, attacked.output
    assert reads.count == 1
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["model"]["source"]["input"] == "bgr255"
    evaluated = invoke(["evaluate", "--weather", out, "--model", f"{net}:decorated", "-q"])
    assert evaluated.exit_code == 0, evaluated.output
    assert reads.count == 2                             # one more run, one more read
    benchmark = invoke(["benchmark", "--networks", f"{net}:decorated", "--presets", "snow",
                        "--lp", "ifgsm", "--steps", "1", "--lp-steps", "1", "--set", "count=20",
                        *sintel_options, "--out", tmp_path / "b", "--quiet"])
    assert benchmark.exit_code == 0, benchmark.output
    assert reads.count == 3


def test_the_commands_note_an_undeclared_convention_once(nets, sintel_options, tmp_path):
    result = invoke(["attack", "--model", f"{nets}:plain", *sintel_options, "--steps", "1",
                     "--set", "count=20", "--out", tmp_path / "a", "--quiet"])
    notes, _ = cli_lines(result)
    assert result.exit_code == 0, result.output
    assert [n for n in notes if "input convention" in n] == [
        "Note: flow model 'contract_nets.plain' declares no input convention: its frames are "
        "given as RGB in [0, 1] (to say otherwise: its input_range and channel_order, or "
        "--model-input; docs/models.md)"]
    declared = invoke(["attack", "--model", f"{nets}:plain", "--model-input", "rgb",
                       *sintel_options, "--steps", "1", "--set", "count=20", "--out",
                       tmp_path / "b", "--quiet"])
    assert declared.exit_code == 0 and "input convention" not in declared.output


def test_a_name_that_is_not_a_python_file_is_refused(tmp_path):
    notes = tmp_path / "notes.txt"
    notes.write_text("import os\nbuild = os.remove\n")
    for name in (f"{notes}:build", "notes.txt:build"):
        with pytest.raises(ConfigError, match="is not a .py file"):
            resolve_network(name) if "/" in name else _in(tmp_path, name)
    result = invoke(["attack", "--model", f"{notes}:build", "--out", tmp_path / "o"])
    assert result.exit_code == 2 and result.output.startswith("Error: --model")
    assert len(result.output.strip().splitlines()) == 1 and notes.exists()


def _in(folder: Path, name: str):
    import os

    here = os.getcwd()
    os.chdir(folder)
    try:
        return resolve_network(name)
    finally:
        os.chdir(here)


def test_a_record_built_in_another_process_reads_the_file_and_refuses_changed_content(tmp_path):
    """A Ray worker gets the record, not the module: it reads the file again, and refuses it when
    its content is no longer the one the run started with."""
    net = tmp_path / "moved.py"
    net.write_text(NETWORKS)
    network = resolve_network(f"{net}:plain")
    module = type(get_model(network).network).__module__
    del sys.modules[module]                                  # as in a fresh process
    assert isinstance(get_model(network), ModuleFlowModel) and module in sys.modules
    del sys.modules[module]
    net.write_text(NETWORKS.replace("0.5", "0.75"))
    with pytest.raises(ConfigError, match="changed since the run started"):
        get_model(network)
