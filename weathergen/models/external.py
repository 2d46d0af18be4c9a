"""Flow networks from outside the package: a Python file, an importable module, an entry point.

A network that weathergen does not ship is named where a registered name would go
(``get_model``, ``--model``, ``benchmark --networks``)::

    FILE.py:NAME            NAME defined in the Python file FILE.py
    package.module:NAME     NAME of an importable module
    NAME                    an entry point of the group ``weathergen.models`` of an installed
                            distribution (``mynet = "mypackage.flow:build"``)

``NAME`` is one of

- a :class:`~weathergen.models.base.FlowModel` subclass: instantiated, its own ``normalize``,
  ``predict``, padding (``multiple``, ``min_size``) and mixed-precision mode (``supports_amp``)
  apply;
- a callable returning a ``torch.nn.Module`` (a function, an ``nn.Module`` subclass) or a
  ``FlowModel``; an ``nn.Module`` instance is used as it is (a copy of it). A plain module maps
  ``(image1, image2)`` ``(B, 3, H, W)`` RGB in ``[0, 1]`` to the flow ``(B, 2, H, W)`` in pixels,
  and is wrapped in :class:`ModuleFlowModel`, which pads the frames to the module's ``multiple``
  and ``min_size`` attributes (1 and 0 where it has none) and crops the flow back.

Keyword arguments ``iters`` and ``gradient_checkpointing`` are passed to NAME where its signature
takes them (``iters`` only when given). A network is checked once when it is loaded: it runs on
one small pair of zeros and must answer a flow of the frames' shape.

What identifies the network in a manifest (:func:`network_record`): the kind, the file (resolved
path) or module and the attribute, the sha256 of the file that defines NAME (for an entry point
also the distribution and its version), so that a run is resumed only with the same code.
"""

from __future__ import annotations

import copy
import hashlib
import importlib
import importlib.metadata
import importlib.util
import inspect
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from ..errors import ConfigError, ShapeError, WeatherGenError
from .base import FlowModel, autocast_mode, mixed_precision
from .checkpoints import load_strict

#: The entry-point group through which installed distributions offer networks.
ENTRY_POINT_GROUP = "weathergen.models"
#: Side of the zero frames an external network is checked with when it is loaded (raised to the
#: network's ``min_size``).
PROBE_SIDE = 64

_MODULE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


@dataclass(frozen=True)
class NetworkSource:
    """Where an external network comes from.

    kind: ``file``, ``module`` or ``entry-point``; spec: the name as given; attribute: NAME;
    path: the Python file that defines NAME (resolved); module: the module's import name;
    sha256: the file's content hash (None for a module without a file); entry_point:
    ``name = value`` of an entry point; distribution: ``name version`` of its distribution.
    """

    kind: str
    spec: str
    attribute: str
    path: Optional[str] = None
    module: Optional[str] = None
    sha256: Optional[str] = None
    entry_point: Optional[str] = None
    distribution: Optional[str] = None

    @property
    def canonical(self) -> str:
        """The name that means the same network from any working directory: ``PATH:NAME`` with
        the resolved path for a file, the name as given otherwise."""
        return f"{self.path}:{self.attribute}" if self.kind == "file" else self.spec

    @property
    def label(self) -> str:
        """A short name fit for a folder or a table column: ``stem.NAME`` for a file,
        ``module.NAME`` for a module, the entry point's name (:func:`spec_label`)."""
        return spec_label(self.spec)

    def record(self) -> dict:
        """The manifest's record of the network's code."""
        return {"kind": self.kind, "path": self.path, "module": self.module,
                "attribute": self.attribute, "sha256": self.sha256,
                "entry_point": self.entry_point, "distribution": self.distribution}


@dataclass
class _Loaded:
    source: NetworkSource
    target: object


def is_external(name) -> bool:
    """Whether ``name`` is a ``FILE.py:NAME`` or ``module:NAME`` network (entry points are looked
    up by :func:`entry_point` once the registry does not know the name)."""
    return isinstance(name, (str, Path)) and ":" in str(name)


def parse_spec(spec: str) -> tuple[str, str, str]:
    """``(kind, target, attribute)`` of ``FILE.py:NAME`` (kind ``file``) or ``module:NAME``
    (kind ``module``).

    Raises:
        ConfigError: no NAME after the colon, or a module part that is neither a file nor a
            dotted module name.
    """
    target, _, attribute = str(spec).rpartition(":")
    if not target or not attribute.isidentifier():
        raise ConfigError(f"${{model}} {spec!r}: expected FILE.py:NAME or package.module:NAME, "
                          f"NAME a Python name")
    if target.endswith(".py") or "/" in target or "\\" in target:
        return "file", target, attribute
    if not _MODULE_NAME.match(target):
        raise ConfigError(f"${{model}} {spec!r}: {target!r} is neither a .py file nor a module name")
    return "module", target, attribute


def spec_label(spec) -> str:
    """The short label of a name (no code is loaded): ``stem.NAME`` of ``FILE.py:NAME``,
    ``module.NAME`` of ``module:NAME``, any other name as it is."""
    if not is_external(spec):
        return str(spec)
    kind, target, attribute = parse_spec(str(spec))
    stem = Path(target).stem if kind == "file" else target
    return f"{stem}.{attribute}"


def resolved_spec(spec):
    """``spec`` with a file network's path resolved (``/abs/path/FILE.py:NAME``), so that it names
    the same file from any working directory; any other name as given. Loads nothing."""
    if not is_external(spec):
        return spec
    kind, target, attribute = parse_spec(str(spec))
    if kind != "file":
        return str(spec)
    return f"{Path(target).expanduser().resolve()}:{attribute}"


def entry_points() -> dict:
    """The entry points of group :data:`ENTRY_POINT_GROUP` of the installed distributions, by
    name (the first of a name wins)."""
    found = {}
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep)
    return found


def entry_point(name: str):
    """The entry point called ``name``, or None."""
    return entry_points().get(name)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _load_file(spec: str, target: str, attribute: str) -> _Loaded:
    path = Path(target).expanduser()
    if not path.is_file():
        what = "is a folder" if path.is_dir() else "does not exist"
        raise ConfigError(f"${{model}} {spec!r}: the file {str(path)!r} {what}")
    path = path.resolve()
    data = path.read_bytes()
    digest = _sha256(data)
    module_name = f"weathergen_network_{path.stem.replace('-', '_')}_{digest[:12]}"
    module = sys.modules.get(module_name)
    if module is None:
        module = _exec_file(spec, path, data, module_name)
    source = NetworkSource("file", spec, attribute, path=str(path), sha256=digest)
    return _Loaded(source, _attribute(module, attribute, spec, str(path)))


def _exec_file(spec: str, path: Path, data: bytes, module_name: str):
    """Run the file's code as module ``module_name``, its folder first on ``sys.path`` meanwhile
    (so that it imports the modules beside it)."""
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
        try:
            sys.path.remove(str(path.parent))
        except ValueError:
            pass
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


def _load_module(spec: str, target: str, attribute: str, kind: str = "module",
                 entry: Optional[str] = None, distribution: Optional[str] = None) -> _Loaded:
    try:
        module = importlib.import_module(target)
    except ModuleNotFoundError as exc:
        if exc.name and (target == exc.name or target.startswith(exc.name + ".")):
            raise ConfigError(f"${{model}} {spec!r}: no module named {exc.name!r} "
                              f"(not installed, or not on the Python path)") from None
        raise ConfigError(f"${{model}} {spec!r}: importing {target} failed: {_one_line(exc)}") from None
    except Exception as exc:
        raise ConfigError(f"${{model}} {spec!r}: importing {target} failed: {_one_line(exc)}") from None
    found = _attribute(module, attribute, spec, f"module {target}")
    path = getattr(module, "__file__", None)
    digest = _sha256(Path(path).read_bytes()) if path and Path(path).is_file() else None
    source = NetworkSource(kind, spec, attribute, path=str(Path(path).resolve()) if path else None,
                           module=target, sha256=digest, entry_point=entry,
                           distribution=distribution)
    return _Loaded(source, found)


def load_network(spec: str) -> _Loaded:
    """The object an external name names and where it comes from.

    Raises:
        ConfigError: a missing file or module, a failing import, a missing attribute, an unknown
            entry point.
    """
    spec = str(spec)
    if is_external(spec):
        kind, target, attribute = parse_spec(spec)
        if kind == "file":
            return _load_file(spec, target, attribute)
        return _load_module(spec, target, attribute)
    ep = entry_point(spec)
    if ep is None:
        raise ConfigError(f"unknown flow model {spec!r}")
    target, _, attribute = ep.value.partition(":")
    if not attribute:
        raise ConfigError(f"${{model}} {spec!r}: the entry point {ep.name} = {ep.value!r} names a "
                          f"module; it must name a network, 'module:NAME'")
    dist = getattr(ep, "dist", None)
    distribution = f"{dist.metadata['Name']} {dist.version}" if dist is not None else None
    return _load_module(spec, target.strip(), attribute.strip(), kind="entry-point",
                        entry=f"{ep.name} = {ep.value}", distribution=distribution)


def network_source(spec: str) -> NetworkSource:
    """Where the external network ``spec`` comes from (loads it)."""
    return load_network(spec).source


class ModuleFlowModel(FlowModel):
    """A plain ``nn.Module`` behind the flow-model contract.

    The module sees the frames as given (RGB in ``[0, 1]``), padded to its ``multiple`` (and at
    least ``min_size``), and answers the flow ``(B, 2, H, W)`` in pixels. In ``bf16``/``fp16``
    (:attr:`~weathergen.models.base.FlowModel.precision`) it runs under autocast and its flow is
    taken back to float32; with
    ``gradient_checkpointing`` and a module without its own (no ``gradient_checkpointing``
    attribute) its whole forward pass is recomputed in the backward pass.
    """

    supports_amp = True

    def __init__(self, network: nn.Module, label: str, gradient_checkpointing: bool = False):
        super().__init__()
        self.network = network
        self.architecture = label
        self.multiple = _positive_int(network, "multiple", 1, label)
        self.min_size = _positive_int(network, "min_size", 0, label)
        own = hasattr(network, "gradient_checkpointing")
        if own and gradient_checkpointing:
            network.gradient_checkpointing = True
        self.recompute = gradient_checkpointing and not own

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        return image

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


def external_network(spec: str, iters: Optional[int] = None,
                     gradient_checkpointing: bool = False) -> FlowModel:
    """An adapter of the external network ``spec`` (weights as NAME makes them), in eval mode.

    Raises:
        ConfigError: see :func:`load_network`; NAME is not callable, or returns something that is
            not a ``torch.nn.Module``.
    """
    loaded = load_network(spec)
    target, label = loaded.target, loaded.source.label
    if isinstance(target, nn.Module):
        made = copy.deepcopy(target)
    elif not callable(target):
        raise ConfigError(f"${{model}} {spec!r}: {loaded.source.attribute!r} is not callable (a "
                          f"value of type {type(target).__name__}); expected a callable returning "
                          f"a torch.nn.Module")
    else:
        made = _call_with(target, spec, iters=iters,
                          gradient_checkpointing=gradient_checkpointing or None)
    if isinstance(made, FlowModel):
        model = made
        if not model.architecture:
            model.architecture = label
    elif isinstance(made, nn.Module):
        model = ModuleFlowModel(made, label, gradient_checkpointing)
    else:
        raise ConfigError(f"${{model}} {spec!r}: {loaded.source.attribute}() returned a value of "
                          f"type {type(made).__name__}, expected a torch.nn.Module")
    return model.eval()


def supports_amp(spec: str) -> bool:
    """Whether the external network has a mixed-precision mode: a FlowModel subclass says so
    itself (``supports_amp``); any other module runs under CUDA autocast as a whole."""
    target = load_network(spec).target
    if inspect.isclass(target) and issubclass(target, FlowModel):
        return bool(target.supports_amp)
    if isinstance(target, FlowModel):
        return bool(target.supports_amp)
    return True


def check_network(model: FlowModel, spec: str, device) -> None:
    """Run ``model`` once on a pair of zero frames (side :data:`PROBE_SIDE`, at least its
    ``min_size``): it must answer a flow tensor of the frames' shape.

    Raises:
        ShapeError: a flow of another shape or type, naming the network.
        ConfigError: the forward pass itself failed.
    """
    side = max(PROBE_SIDE, int(getattr(model, "min_size", 0) or 0))
    images = torch.zeros(1, 3, side, side, device=device)
    try:
        with torch.no_grad():
            flow = model(images, images)
    except WeatherGenError:
        raise
    except Exception as exc:
        raise ConfigError(f"${{model}} {spec!r}: running it on a (1, 3, {side}, {side}) pair of "
                          f"frames failed: {_one_line(exc)}") from None
    if tuple(flow.shape) != (1, 2, side, side):
        raise ShapeError(f"flow model {spec!r} returned a flow of shape {tuple(flow.shape)} for "
                         f"frames (1, 3, {side}, {side}), expected (1, 2, {side}, {side})")
