"""Networks from outside the package: a file the test writes (``FILE.py:NAME``), a module on the
path (``package.module:NAME``) and an entry point of a distribution the test fakes (a dist-info
folder on ``sys.path``); the library and the commands (attack, evaluate, benchmark, models) with
them, the manifest's record of their code, and every error a user can make naming one."""

from __future__ import annotations

import json
import sys
import textwrap

import pytest
import torch
from model_checks import attack_then_evaluate, invoke, tiny_sintel

from weathergen.errors import ConfigError, ShapeError
from weathergen.models import (FlowModel, ModuleFlowModel, available_models, get_model, resolve_amp,
                               resolve_network)

#: A few convolutions: a plain module, a FlowModel subclass, and the error cases.
NETWORKS = textwrap.dedent('''
    import torch
    from torch import nn
    from weathergen.models import FlowModel

    SEEN = []          # the frame shapes the module was called with

    class Convs(nn.Module):
        multiple = 8

        def __init__(self, width=8):
            super().__init__()
            self.body = nn.Sequential(nn.Conv2d(6, width, 3, padding=1), nn.ReLU(),
                                      nn.Conv2d(width, 2, 3, padding=1))

        def forward(self, image1, image2):
            SEEN.append(tuple(image1.shape))
            return 4.0 * self.body(torch.cat([image1, image2], 1))

    def make(iters=None):
        torch.manual_seed(0)
        net = Convs()
        net.iters_seen = iters
        return net

    class Shift(FlowModel):
        """Its own adapter: frames in [-1, 1], padded to 16, a learnt constant flow."""
        multiple = 16

        def __init__(self):
            super().__init__()
            self.flow = nn.Parameter(torch.tensor([1.5, -0.5]))

        def normalize(self, image):
            return 2 * image - 1

        def predict(self, image1, image2):
            assert image1.shape[-1] % 16 == 0 and image1.min() >= -1
            b, _, h, w = image1.shape
            return (self.flow[None, :, None, None] + 0 * (image1 + image2)[:, :2]).expand(b, 2, h, w)

    def not_a_module():
        return {"flow": 0}

    LIMIT = 3

    class Quarter(nn.Module):
        def forward(self, image1, image2):
            return image1[:, :2, ::4, ::4]

    class Pair(nn.Module):
        def forward(self, image1, image2):
            return [image1[:, :2], image2[:, :2]]

    def broken():
        raise RuntimeError("no weights here")
''')


@pytest.fixture(scope="module")
def net_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("nets") / "my_nets.py"
    path.write_text(NETWORKS)
    return path


@pytest.fixture
def installed(tmp_path, monkeypatch):
    """A distribution ``fakenets`` 1.0 on ``sys.path`` whose entry point ``tinyflow`` (group
    weathergen.models) names ``fakenets.flows:make``, and whose ``broken`` names a module."""
    site = tmp_path / "site"
    package = site / "fakenets"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "flows.py").write_text(NETWORKS)
    dist = site / "fakenets-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: fakenets\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(
        "[weathergen.models]\ntinyflow = fakenets.flows:make\nbroken = fakenets.flows\n")
    monkeypatch.syspath_prepend(str(site))
    yield site
    for name in [m for m in sys.modules if m == "fakenets" or m.startswith("fakenets.")]:
        del sys.modules[name]


def flow_of(model, size=(30, 45), batch=2):
    x1, x2 = torch.rand(2, batch, 3, *size, generator=torch.Generator().manual_seed(0)).unbind(0)
    with torch.no_grad():
        return model(x1, x2)


# -- the library -------------------------------------------------------------------------------

def test_a_plain_module_in_a_file_is_padded_to_its_multiple_and_batched(net_file):
    model = get_model(f"{net_file}:make")
    assert isinstance(model, ModuleFlowModel) and model.multiple == 8
    module = sys.modules[type(model.network).__module__]
    module.SEEN.clear()
    flow = flow_of(model, size=(30, 45), batch=2)
    assert flow.shape == (2, 2, 30, 45)
    assert module.SEEN == [(2, 3, 32, 48)]            # padded to multiples of 8, both pairs at once
    assert not any(p.requires_grad for p in model.parameters())
    # the same as the module on the padded frames, cropped (even padding: 1 row, 1 + 2 columns)
    x1, x2 = torch.rand(2, 1, 3, 30, 45).unbind(0)
    pad = lambda x: torch.nn.functional.pad(x, (1, 2, 1, 1), mode="replicate")   # noqa: E731
    with torch.no_grad():
        direct = model.network(pad(x1), pad(x2))[..., 1:31, 1:46]
        assert torch.allclose(model(x1, x2), direct)


def test_iters_reach_a_callable_that_takes_them_and_a_flowmodel_subclass_keeps_its_adapter(net_file):
    assert get_model(f"{net_file}:make", iters=5).network.iters_seen == 5
    shift = get_model(f"{net_file}:Shift")
    assert isinstance(shift, FlowModel) and shift.multiple == 16
    flow = flow_of(shift, size=(20, 21), batch=1)
    assert torch.allclose(flow[0, :, 3, 4], torch.tensor([1.5, -0.5]))


def test_a_checkpoint_file_is_loaded_into_the_module_strictly(net_file, tmp_path):
    state = {k: torch.full_like(v, 0.01) for k, v in get_model(f"{net_file}:make").network.state_dict().items()}
    torch.save(state, tmp_path / "w.pth")
    loaded = get_model(f"{net_file}:make", checkpoint=tmp_path / "w.pth")
    assert all(torch.equal(v, state[k]) for k, v in loaded.network.state_dict().items())
    torch.save({"body.0.weight": state["body.0.weight"]}, tmp_path / "part.pth")
    with pytest.raises(Exception, match="missing keys"):
        get_model(f"{net_file}:make", checkpoint=tmp_path / "part.pth")
    with pytest.raises(ConfigError, match="no such file"):
        get_model(f"{net_file}:make", checkpoint=tmp_path / "none.pth")


def test_gradient_checkpointing_recomputes_a_plain_module_with_the_same_gradient(net_file):
    plain = get_model(f"{net_file}:make")
    again = get_model(f"{net_file}:make", gradient_checkpointing=True)
    assert again.recompute and not plain.recompute
    module = sys.modules[type(plain.network).__module__]
    grads = []
    for model in (plain, again):
        x1 = torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(3)).requires_grad_()
        module.SEEN.clear()
        model(x1, x1.detach().flip(-1)).square().sum().backward()
        grads.append(x1.grad)
        assert len(module.SEEN) == (2 if model is again else 1)     # forward run again in backward
    assert torch.allclose(grads[0], grads[1])


def test_mixed_precision_of_external_networks(net_file):
    """A plain module may run under autocast (asked for on CUDA only); a FlowModel subclass says
    itself whether it can."""
    name = f"{net_file}:make"
    assert resolve_amp(name, None, "cuda") is False and resolve_amp(name, True, "cuda") is True
    with pytest.raises(ConfigError, match="needs a CUDA device"):
        resolve_amp(name, True, "cpu")
    with pytest.raises(ConfigError, match="no mixed-precision mode"):
        resolve_amp(f"{net_file}:Shift", True, "cuda")


@pytest.mark.cuda
def test_a_plain_module_runs_under_autocast_on_cuda(net_file):
    model = get_model(f"{net_file}:make", device="cuda", amp=True)
    x = torch.rand(1, 3, 24, 24, device="cuda")
    with torch.no_grad():
        flow = model(x, x)
    assert flow.dtype == torch.float32 and flow.shape == (1, 2, 24, 24)


def test_a_module_on_the_path_and_an_installed_entry_point(net_file, installed):
    module_net = get_model("fakenets.flows:make")
    entry_net = get_model("tinyflow")
    x = flow_of(module_net)
    assert torch.equal(x, flow_of(entry_net)) and torch.equal(x, flow_of(get_model(f"{net_file}:make")))
    record = resolve_network("tinyflow").source()
    assert record["kind"] == "entry-point" and record["distribution"] == "fakenets 1.0"
    assert record["entry_point"] == "tinyflow = fakenets.flows:make" and len(record["sha256"]) == 64
    assert resolve_network("tinyflow").label == "tinyflow"
    assert resolve_network("fakenets.flows:make").label == "fakenets.flows.make"
    assert "tinyflow" not in available_models()       # the shipped registry stays as it is


def test_the_record_of_a_file_network_names_its_path_and_content(net_file, tmp_path):
    network = resolve_network(f"{net_file}:make")
    record = network.source()
    import hashlib

    assert record["kind"] == "file" and record["path"] == str(net_file.resolve())
    assert record["sha256"] == hashlib.sha256(net_file.read_bytes()).hexdigest()
    assert network.label == "my_nets.make" and network.name == f"{net_file.resolve()}:make"


@pytest.mark.parametrize("name, error, words", [
    ("{dir}/none.py:make", ConfigError, "does not exist"),
    ("{file}:missing", ConfigError, "has no 'missing' (it defines"),
    ("{file}:not_a_module", ConfigError, "returned a value of type dict, expected a torch.nn.Module"),
    ("{file}:LIMIT", ConfigError, "'LIMIT' is not callable (a value of type int)"),
    ("{file}:Quarter", ShapeError, "returned a flow of shape (1, 2, 16, 16)"),
    ("{file}:Pair", ShapeError, "returned a value of type list"),
    ("{file}:broken", ConfigError, "calling it failed: RuntimeError: no weights here"),
    ("{dir}/syntax.py:make", ConfigError, "SyntaxError"),
    ("no_such_package.flows:make", ConfigError, "no module named 'no_such_package'"),
    ("{file}", ConfigError, "FILE.py:NAME"),
    ("{file}:", ConfigError, "expected FILE.py:NAME"),
])
def test_every_bad_name_is_one_clear_error(name, error, words, net_file):
    (net_file.parent / "syntax.py").write_text("def make(:\n")
    spec = name.format(file=net_file, dir=net_file.parent)
    with pytest.raises(error) as caught:
        get_model(spec)
    assert words in str(caught.value) and "\n" not in str(caught.value)


def test_an_entry_point_that_names_a_module_is_refused(installed):
    with pytest.raises(ConfigError, match="names a module; it must name a network"):
        get_model("broken")


# -- the commands ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def sintel_options(tmp_path_factory):
    return tiny_sintel(tmp_path_factory.mktemp("sintel"))


@pytest.mark.slow
def test_attack_and_evaluate_with_a_file_network(net_file, sintel_options, tmp_path):
    summary, manifest, result = attack_then_evaluate(["--model", f"{net_file}:make"],
                                                     sintel_options, tmp_path)
    assert summary["pairs"] == 1
    model = manifest["config"]["model"]
    assert model["name"] == f"{net_file.resolve()}:make"
    assert model["source"]["path"] == str(net_file.resolve()) and len(model["source"]["sha256"]) == 64
    assert result["source"] == model["source"]
    (row,) = result["pairs"]
    assert row["aee_weather"] == pytest.approx(summary["aee_adversarial"], rel=1e-4, abs=1e-5)
    # the default name of evaluate's file: the network's short label
    again = invoke(["evaluate", "--weather", tmp_path / "snow", "--model", f"{net_file}:make", "-q"])
    assert again.exit_code == 0 and (tmp_path / "snow" / "evaluate-my_nets.make.json").is_file()


@pytest.mark.slow
def test_resuming_with_an_edited_file_is_refused(net_file, sintel_options, tmp_path):
    copy = tmp_path / "net.py"
    copy.write_text(NETWORKS)
    args = ["attack", "--model", f"{copy}:make", *sintel_options, "--steps", "1", "--set",
            "count=20", "--out", tmp_path / "out", "--quiet"]
    assert invoke(args).exit_code == 0
    copy.write_text(NETWORKS.replace("4.0 *", "3.0 *"))
    refused = invoke([*args, "--resume"])
    assert refused.exit_code == 2 and "different settings (model)" in refused.output


@pytest.mark.slow
def test_attack_evaluate_and_benchmark_with_an_installed_network(installed, net_file, sintel_options,
                                                                tmp_path):
    summary, manifest, result = attack_then_evaluate(["--model", "tinyflow"], sintel_options,
                                                     tmp_path)
    assert manifest["config"]["model"]["source"]["distribution"] == "fakenets 1.0"
    out = tmp_path / "bench"
    ran = invoke(["benchmark", "--networks", f"tinyflow,{net_file}:make", "--presets", "snow",
                  "--lp", "", "--steps", "1", "--set", "count=20", *sintel_options, "--out", out,
                  "--quiet"])
    assert ran.exit_code == 0, ran.output
    doc = json.loads((out / "results.json").read_text())
    assert [r["network"] for r in doc["networks"]] == ["tinyflow", f"{net_file}:make"]
    assert doc["networks"][1]["source"]["path"] == str(net_file.resolve())
    assert (out / "runs" / "my_nets.make" / "snow" / "summary.json").is_file()
    assert (out / "runs" / "tinyflow" / "snow" / "summary.json").is_file()
    head = (out / "tables" / "weatherattacks.md").read_text().splitlines()[2]
    assert head.index("tinyflow") < head.index("my_nets.make")     # the command line's order


def library_attack_and_evaluate(name, dataset, out):
    """``run_attack`` with the network ``name`` (one step, 20 snow particles), then
    ``run_evaluation`` of its output with the same network. Returns the summary and the figures."""
    from weathergen.attack import AttackJob, plan_attack, run_attack, run_evaluation
    from weathergen.outputs import WeatherFolder

    plan = plan_attack(None, "snow", {"count": "20"}, steps=1)
    summary = run_attack(AttackJob(dataset=dataset, out=out, model=name, checkpoint=None,
                                   preset=plan.preset, preset_name=plan.preset_name,
                                   settings=plan.settings))
    rows, figures = run_evaluation(get_model(name), WeatherFolder.open(out), dataset)
    return summary, rows, figures


def test_the_library_runs_an_attack_and_a_benchmark_with_a_file_network(net_file, sintel_options,
                                                                       tmp_path):
    from weathergen.benchmark import BenchmarkSpec, run_grid
    from weathergen.datasets import open_dataset

    root = sintel_options[sintel_options.index("--root") + 1]
    dataset = open_dataset("sintel", root, scenes=["alley"], frames_per_scene=1)
    summary, rows, figures = library_attack_and_evaluate(f"{net_file}:make", dataset, tmp_path / "a")
    assert summary["pairs"] == 1 and len(rows) == 1 and figures["pairs"] == 1
    # the network evaluated on the attack's written (8-bit) frames: the attack's figure, nearly
    assert figures["aee_weather"] == pytest.approx(summary["aee_adversarial"], rel=1e-3, abs=1e-4)
    spec = BenchmarkSpec(dataset=dataset, out=tmp_path / "b", networks=[f"{net_file}:Shift"],
                         presets=["snow"], lp_methods=["ifgsm"], steps=1, lp_steps=1,
                         overrides={"count": "20"})
    cells = run_grid(spec)
    assert [c.folder(spec.out).relative_to(spec.out).as_posix() for c in cells] == \
        ["runs/my_nets.Shift/snow", "runs/my_nets.Shift/ifgsm"]


def test_the_library_runs_an_attack_evaluate_and_benchmark_with_an_installed_network(
        installed, net_file, sintel_options, tmp_path):
    from weathergen.benchmark import BenchmarkSpec, run_grid
    from weathergen.datasets import open_dataset

    root = sintel_options[sintel_options.index("--root") + 1]
    dataset = open_dataset("sintel", root, scenes=["alley"], frames_per_scene=1)
    summary, rows, figures = library_attack_and_evaluate("tinyflow", dataset, tmp_path / "a")
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert manifest["config"]["model"]["source"]["entry_point"] == "tinyflow = fakenets.flows:make"
    assert summary["pairs"] == 1 and figures["pairs"] == 1
    assert figures["aee_weather"] == pytest.approx(summary["aee_adversarial"], rel=1e-3, abs=1e-4)
    # the entry point's network is the module's own: the same figures as the file's network
    _, _, same = library_attack_and_evaluate(f"{net_file}:make", dataset, tmp_path / "f")
    assert figures["aee_weather"] == same["aee_weather"]
    spec = BenchmarkSpec(dataset=dataset, out=tmp_path / "b", networks=["tinyflow"],
                         presets=["snow"], lp_methods=[], steps=1, overrides={"count": "20"})
    (cell,) = run_grid(spec)
    assert cell.folder(spec.out).relative_to(spec.out).as_posix() == "runs/tinyflow/snow"
    assert json.loads((spec.out / "runs" / "tinyflow" / "snow" / "summary.json").read_text())["pairs"] == 1


def test_the_models_command_lists_networks_checkpoints_and_installed_ones(installed, net_file):
    listing = invoke(["models"])
    assert listing.exit_code == 0
    for name in ("raft-small", "raft-sintel", "flowformer", "tinyflow", "fakenets 1.0",
                 "fakenets.flows:make"):
        assert name in listing.output
    assert "names a module" in listing.output                 # the broken entry point, said
    assert "raft-small*" in listing.output        # shipped with the package (the cache is empty)
    one = invoke(["models", f"{net_file}:make"])
    assert one.exit_code == 0 and "sha256" in one.output and "8, 0" in one.output
    raft = invoke(["models", "raft-kitti"])
    assert raft.exit_code == 0 and "raft-things" in raft.output


@pytest.fixture(scope="module")
def weather_folder(sintel_options, tmp_path_factory):
    out = tmp_path_factory.mktemp("render") / "snow"
    rendered = invoke(["render", *sintel_options, "--set", "count=20", "--out", out, "--quiet"])
    assert rendered.exit_code == 0, rendered.output
    return out


@pytest.mark.parametrize("command", ["attack", "evaluate", "benchmark"])
def test_the_commands_say_a_bad_network_in_one_line(command, net_file, sintel_options,
                                                    weather_folder, tmp_path):
    option = "--networks" if command == "benchmark" else "--model"
    extra = (["--weather", weather_folder] if command == "evaluate"
             else [*sintel_options, "--out", tmp_path / "o"])
    for name, words in ((f"{net_file}:Quarter", "returned a flow of shape"),
                        (f"{net_file.parent}/gone.py:make", "does not exist"),
                        (f"{net_file}:missing", "has no 'missing'"),
                        (f"{net_file}:not_a_module", "expected a torch.nn.Module")):
        result = invoke([command, option, name, *extra])
        assert result.exit_code == 2, result.output
        lines = [t for t in result.output.strip().splitlines() if not t.startswith("Note:")]
        assert len(lines) == 1 and lines[0].startswith("Error:") and words in lines[0], result.output
        assert "--model " not in lines[0] if command == "benchmark" else "--networks" not in lines[0]
        assert not (tmp_path / "o").exists()              # nothing written


def test_a_library_attack_gives_back_the_callers_torch_threads(net_file, sintel_options, tmp_path):
    """An attack run with its own thread count (``AttackJob.threads``) restores the caller's."""
    from weathergen.attack import AttackJob, plan_attack, run_attack
    from weathergen.datasets import open_dataset

    root = sintel_options[sintel_options.index("--root") + 1]
    dataset = open_dataset("sintel", root, scenes=["alley"], frames_per_scene=1)
    plan = plan_attack(None, "snow", {"count": "20"}, steps=1)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        summary = run_attack(AttackJob(dataset=dataset, out=tmp_path / "a", model=f"{net_file}:make",
                                       checkpoint=None, preset=plan.preset,
                                       preset_name=plan.preset_name, settings=plan.settings,
                                       threads=1))
        assert summary["pairs"] == 1
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
