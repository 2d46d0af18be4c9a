"""Flow networks from outside the package: a Python file, an importable module, an entry point.

A network that weathergen does not ship is named where a registered name would go
(``get_model``, ``--model``, ``benchmark --networks``): ``FILE.py:NAME`` (NAME defined in the
Python file), ``package.module:NAME``, or the name of an entry point of the group
``weathergen.models`` (``mynet = "mypackage.flow:build"``). NAME is a
:class:`~weathergen.models.base.FlowModel` subclass (its own conventions apply), or a callable
returning an ``nn.Module`` or a ``FlowModel`` (an ``nn.Module`` instance is copied). A plain
module is wrapped in :class:`ModuleFlowModel`: padded to its ``multiple`` and ``min_size``, given
the frames in its input convention (:func:`flow_input`), its flow cropped back.

:func:`load_source` reads and runs the code once, when the name is resolved
(:func:`~weathergen.models.resolve_network`); :func:`target_of` finds the object again from the
record without reading the file (another process reads it again, and refuses changed content).
:func:`probe_network` refuses a flow that is not finite or gives no gradient to the frames.
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import importlib
import importlib.metadata
import importlib.util
import inspect
import re
import sys
from pathlib import Path
from typing import Callable, Optional

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from ..errors import ConfigError, WeatherGenError
from .base import FlowModel, autocast_mode, mixed_precision
from .checkpoints import load_strict

#: The entry-point group through which installed distributions offer networks.
ENTRY_POINT_GROUP = "weathergen.models"
#: Side of the random frames a network from outside the package is checked with when it is
#: loaded (raised to the network's ``min_size``).
PROBE_SIDE = 64
#: The input conventions a plain module may declare: name -> (channel order, range maximum).
INPUT_CONVENTIONS = {"rgb": ("RGB", 1), "bgr": ("BGR", 1), "rgb255": ("RGB", 255),
                     "bgr255": ("BGR", 255)}

_MODULE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


def is_external(name) -> bool:
    """Whether ``name`` is a ``FILE.py:NAME`` or ``module:NAME`` network (entry points are looked
    up among :func:`entry_points` once the registry does not know the name)."""
    return isinstance(name, (str, Path)) and ":" in str(name)


def parse_spec(spec: str) -> tuple[str, str, str]:
    """``(kind, target, attribute)`` of ``FILE.py:NAME`` (kind ``file``) or ``module:NAME``
    (kind ``module``).

    Raises:
        ConfigError: no NAME after the colon, a file that is not a ``.py`` file, or a module part
            that is neither a file nor a dotted module name.
    """
    target, _, attribute = str(spec).rpartition(":")
    if not target or not attribute.isidentifier():
        raise ConfigError(f"${{model}} {spec!r}: expected FILE.py:NAME or package.module:NAME, "
                          f"NAME a Python name")
    if target.endswith(".py"):
        return "file", target, attribute
    if "/" in target or "\\" in target or Path(target).is_file():
        raise ConfigError(f"${{model}} {spec!r}: {target!r} is not a .py file; a network in a "
                          f"file is named FILE.py:NAME")
    if not _MODULE_NAME.match(target):
        raise ConfigError(f"${{model}} {spec!r}: {target!r} is neither a .py file nor a module name")
    return "module", target, attribute


def network_label(spec) -> str:
    """The short label of a name (no code is loaded): ``stem.NAME`` of ``FILE.py:NAME``,
    ``module.NAME`` of ``module:NAME``, any other name as it is."""
    if not is_external(spec):
        return str(spec)
    kind, target, attribute = parse_spec(str(spec))
    return f"{Path(target).stem if kind == 'file' else target}.{attribute}"


def entry_points() -> dict:
    """The entry points of group :data:`ENTRY_POINT_GROUP` of the installed distributions, by
    name (the first of a name wins)."""
    found = {}
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep)
    return found


def read_source(path: Path) -> bytes:
    """The bytes of a network's Python file: the one place its file is read."""
    return Path(path).read_bytes()


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _module_name(path: Path, digest: str) -> str:
    return f"weathergen_network_{Path(path).stem.replace('-', '_')}_{digest[:12]}"


def load_source(spec: str) -> tuple[dict, object]:
    """``(fields, target)``: the fields of the external network's record (``kind``, ``name``,
    ``attribute``, ``path``, ``module``, ``sha256``, ``entry_point``, ``distribution``; see
    :class:`~weathergen.models.Network`) and the object NAME, its code read and run once.
    ConfigError: a missing file or module, a failing import, a missing attribute."""
    spec = str(spec)
    if is_external(spec):
        kind, target, attribute = parse_spec(spec)
        if kind == "file":
            return _load_file(spec, target, attribute)
        return _load_module(spec, target, attribute, {"kind": "module", "name": spec})
    ep = entry_points().get(spec)
    if ep is None:
        raise ConfigError(f"unknown flow model {spec!r}")
    target, _, attribute = ep.value.partition(":")
    if not attribute:
        raise ConfigError(f"${{model}} {spec!r}: the entry point {ep.name} = {ep.value!r} names a "
                          f"module; it must name a network, 'module:NAME'")
    dist = getattr(ep, "dist", None)
    return _load_module(spec, target.strip(), attribute.strip(), {
        "kind": "entry-point", "name": spec, "entry_point": f"{ep.name} = {ep.value}",
        "distribution": f"{dist.metadata['Name']} {dist.version}" if dist is not None else None})


def _load_file(spec: str, target: str, attribute: str,
               recorded: Optional[str] = None) -> tuple[dict, object]:
    """The file's record and NAME; with the ``recorded`` sha256 the module this process ran from
    it, without reading it again, or (another process) the file if its content is unchanged."""
    path = Path(target).expanduser()
    module = sys.modules.get(_module_name(path, recorded)) if recorded else None
    if module is None:
        if not path.is_file():
            what = "is a folder" if path.is_dir() else "does not exist"
            raise ConfigError(f"${{model}} {spec!r}: the file {str(path)!r} {what}")
        path = path.resolve()
        data = read_source(path)
        digest = _sha256(data)
        if recorded not in (None, digest):
            raise ConfigError(f"${{model}} {spec!r}: {path} changed since the run started "
                              f"(sha256 {digest[:12]}…, recorded {recorded[:12]}…)")
        module = sys.modules.get(_module_name(path, digest)) or _exec_file(spec, path, data, digest)
    fields = {"kind": "file", "name": f"{path}:{attribute}", "attribute": attribute,
              "path": str(path), "sha256": recorded or digest}
    return fields, _attribute(module, attribute, spec, str(path))


def _exec_file(spec: str, path: Path, data: bytes, digest: str):
    """Run the file's code as a module named after its content, its folder first on
    ``sys.path`` meanwhile (so that it imports the modules beside it)."""
    module_name = _module_name(path, digest)
    module_spec = importlib.util.spec_from_loader(module_name, loader=None, origin=str(path))
    module = importlib.util.module_from_spec(module_spec)
    module.__file__ = str(path)
    sys.path.insert(0, str(path.parent))
    sys.modules[module_name] = module
    try:
        exec(compile(data, str(path), "exec"), module.__dict__)
    except WeatherGenError:
        sys.modules.pop(module_name, None)
        raise
    except BaseException as exc:       # its own error, whatever it is, said in one line
        sys.modules.pop(module_name, None)
        if isinstance(exc, KeyboardInterrupt):
            raise
        raise ConfigError(f"${{model}} {spec!r}: running {path} failed: {_one_line(exc)}") from None
    finally:
        with contextlib.suppress(ValueError):
            sys.path.remove(str(path.parent))
    return module


def _one_line(exc: BaseException) -> str:
    if isinstance(exc, SyntaxError):
        return f"SyntaxError: {exc.msg} (line {exc.lineno})"
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _attribute(module, attribute: str, spec: str, where: str):
    if not hasattr(module, attribute):
        names = sorted(n for n, v in vars(module).items()
                       if not n.startswith("_") and callable(v)
                       and getattr(v, "__module__", None) == module.__name__)
        defines = f" (it defines {', '.join(names)})" if names else ""
        raise ConfigError(f"${{model}} {spec!r}: {where} has no {attribute!r}{defines}")
    return getattr(module, attribute)


def _import(spec: str, target: str):
    try:
        return importlib.import_module(target)
    except Exception as exc:
        missing = isinstance(exc, ModuleNotFoundError) and exc.name and (
            target == exc.name or target.startswith(exc.name + "."))
        why = (f"no module named {exc.name!r} (not installed, or not on the Python path)" if missing
               else f"importing {target} failed: {_one_line(exc)}")
        raise ConfigError(f"${{model}} {spec!r}: {why}") from None


def _load_module(spec: str, target: str, attribute: str, fields: dict) -> tuple[dict, object]:
    module = _import(spec, target)
    found = _attribute(module, attribute, spec, f"module {target}")
    path = getattr(module, "__file__", None)
    digest = _sha256(read_source(path)) if path and Path(path).is_file() else None
    return {**fields, "attribute": attribute, "path": str(Path(path).resolve()) if path else None,
            "module": target, "sha256": digest}, found


def target_of(network) -> object:
    """The object NAME of a resolved external network (a :class:`~weathergen.models.Network`),
    found again without reading its file where this process has run it (see :func:`_load_file`).
    ConfigError: the file changed or is gone, the module no longer imports."""
    if network.kind == "file":
        return _load_file(network.name, network.path, network.attribute, network.sha256)[1]
    return _attribute(_import(network.name, network.module), network.attribute, network.name,
                      f"module {network.module}")


def is_adapter(target) -> bool:
    """Whether NAME is a :class:`FlowModel` (class or instance): its own conventions and
    mixed-precision mode (``supports_amp``) apply; any other module runs under CUDA autocast as
    a whole."""
    return isinstance(target, FlowModel) or (inspect.isclass(target)
                                             and issubclass(target, FlowModel))


def flow_input(input_range: int = 1, channel_order: str = "RGB"):
    """Declare the input convention of a plain module on its class or on the function that
    builds it (``@flow_input(255, "BGR")``): the attributes ``input_range`` (1 or 255: frames in
    ``[0, 1]`` or ``[0, 255]``) and ``channel_order`` (``"RGB"`` or ``"BGR"``)."""
    def declare(target):
        target.input_range, target.channel_order = input_range, channel_order
        declared_input(target, "flow_input")          # a bad value is said here, at once
        return target
    return declare


def declared_input(target, spec: str) -> Optional[str]:
    """The input convention NAME declares (a key of :data:`INPUT_CONVENTIONS`), None where it
    declares neither ``input_range`` nor ``channel_order``; ConfigError for another value."""
    value, order = getattr(target, "input_range", None), getattr(target, "channel_order", None)
    if value is None and order is None:
        return None
    top = value[1] if isinstance(value, (tuple, list)) and len(value) == 2 else value
    name = str(order or "RGB").lower() + ("255" if top == 255 else "")
    if top not in (None, 1, 255) or isinstance(top, bool) or name not in INPUT_CONVENTIONS:
        raise ConfigError(f"${{model}} {spec!r}: its input_range must be 1 or 255 ([0, 1] or "
                          f"[0, 255]) and its channel_order RGB or BGR, got {value!r}, {order!r}")
    return name


class ModuleFlowModel(FlowModel):
    """A plain ``nn.Module`` behind the flow-model contract.

    The module sees the frames in its input convention (``convention``, a key of
    :data:`INPUT_CONVENTIONS`: RGB in ``[0, 1]`` by default), padded to its ``multiple`` (and at
    least ``min_size``), and answers the flow ``(B, 2, H, W)`` in pixels. In ``bf16``/``fp16``
    (:attr:`~weathergen.models.base.FlowModel.precision`) it runs under autocast and its flow is
    taken back to float32; with
    ``gradient_checkpointing`` and a module without its own (no ``gradient_checkpointing``
    attribute) its whole forward pass is recomputed in the backward pass.
    """

    supports_amp = True

    def __init__(self, network: nn.Module, label: str, gradient_checkpointing: bool = False,
                 convention: str = "rgb"):
        super().__init__()
        self.network = network
        self.architecture = label
        self.convention = convention
        self.multiple = _positive_int(network, "multiple", 1, label)
        self.min_size = _positive_int(network, "min_size", 0, label)
        own = hasattr(network, "gradient_checkpointing")
        if own and gradient_checkpointing:
            network.gradient_checkpointing = True
        self.recompute = gradient_checkpointing and not own

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        order, top = INPUT_CONVENTIONS[self.convention]
        image = image.flip(1) if order == "BGR" else image
        return image * top if top != 1 else image

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        with mixed_precision(autocast_mode(self.precision, image1)):
            if self.recompute and torch.is_grad_enabled():
                flow = recompute(self.network, image1, image2, use_reentrant=False)
            else:
                flow = self.network(image1, image2)
        if isinstance(flow, torch.Tensor) and flow.dtype in (torch.float16, torch.bfloat16):
            return flow.float()
        return flow                     # its type and shape are checked by FlowModel.forward

    def load_checkpoint(self, state_dict: dict, source, what: str) -> None:
        load_strict(self.network, state_dict, source, what)


def _positive_int(network, name: str, default: int, label: str) -> int:
    value = getattr(network, name, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < (1 if name == "multiple" else 0):
        raise ConfigError(f"flow model {label!r}: its {name!r} must be a "
                          f"{'positive' if name == 'multiple' else 'non-negative'} integer, got {value!r}")
    return value


def _call_with(target: Callable, spec: str, **options):
    """``target(**options)`` with the options its signature takes (``None`` values left out)."""
    try:
        params = inspect.signature(target).parameters
    except (TypeError, ValueError):
        params = {}
    var_kw = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    kwargs = {k: v for k, v in options.items() if v is not None and (var_kw or k in params)}
    try:
        return target(**kwargs)
    except WeatherGenError:
        raise
    except Exception as exc:
        raise ConfigError(f"${{model}} {spec!r}: calling it failed: {_one_line(exc)}") from None


def build_external(network, iters: Optional[int] = None,
                   gradient_checkpointing: bool = False) -> FlowModel:
    """An adapter of the resolved external ``network`` (weights as NAME makes them), in eval
    mode; a plain module is given its frames in ``network.input``.

    Raises:
        ConfigError: NAME is not callable, or returns something that is not a ``torch.nn.Module``.
    """
    target, spec, label = target_of(network), network.name, network.label
    if isinstance(target, nn.Module):
        made = copy.deepcopy(target)
    elif not callable(target):
        raise ConfigError(f"${{model}} {spec!r}: {network.attribute!r} is not callable (a value of "
                          f"type {type(target).__name__}); expected a callable returning a "
                          f"torch.nn.Module")
    else:
        made = _call_with(target, spec, iters=iters,
                          gradient_checkpointing=gradient_checkpointing or None)
    if isinstance(made, FlowModel):
        if not made.architecture:
            made.architecture = label
        return made.eval()
    if isinstance(made, nn.Module):
        return ModuleFlowModel(made, label, gradient_checkpointing, network.input or "rgb").eval()
    raise ConfigError(f"${{model}} {spec!r}: {network.attribute}() returned a value of type "
                      f"{type(made).__name__}, expected a torch.nn.Module")


def probe_network(model: FlowModel, name: str, image1: Optional[torch.Tensor] = None,
                  image2: Optional[torch.Tensor] = None, gradient: bool = False) -> None:
    """Run ``model`` once on a pair ``(B, 3, H, W)`` (without one: a random pair of side
    :data:`PROBE_SIDE`, at least the network's ``min_size``, on its device): its flow must have
    the frames' shape (checked by :meth:`FlowModel.forward`) and be finite; with ``gradient``
    (an attack) it must also carry a finite gradient back to the frames.

    Raises:
        ShapeError: a flow of another shape or type, naming the network.
        ConfigError: the forward pass failed, a flow that is not finite, no gradient.
    """
    if image1 is None:
        side = max(PROBE_SIDE, model.min_size)
        device = next(model.parameters(), torch.zeros(())).device
        image1, image2 = torch.rand(2, 1, 3, side, side, generator=torch.Generator().manual_seed(0)
                                    ).to(device).unbind(0)
    size = tuple(image1.shape)
    image1 = image1.detach().clone().requires_grad_(gradient)
    try:
        with torch.set_grad_enabled(gradient):
            flow = model(image1, image2)
    except WeatherGenError:
        raise
    except Exception as exc:
        raise ConfigError(f"${{model}} {name!r}: running it on frames of shape {size} failed: "
                          f"{_one_line(exc)}") from None
    check_finite(flow, name, size)
    if gradient:
        grad = (torch.autograd.grad(flow.float().square().sum(), image1, allow_unused=True)[0]
                if flow.requires_grad else None)
        if grad is None or not torch.isfinite(grad).all():
            raise ConfigError(f"flow model {name!r} gives no{' finite' if grad is not None else ''} "
                              f"gradient to its input frames (does its forward run under "
                              f"torch.no_grad or detach them?): an attack needs one")


def check_finite(flow: torch.Tensor, name: str, size: tuple) -> None:
    """ConfigError naming the network where its flow holds NaN or inf."""
    if not torch.isfinite(flow).all():
        raise ConfigError(f"flow model {name!r} answers a flow that is not finite (NaN or inf) on "
                          f"frames of shape {size}")
