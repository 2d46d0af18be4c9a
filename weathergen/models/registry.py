"""Flow networks and their checkpoints, looked up by name.

Each network lives in one module of this package that, on import, registers

- its architecture with :func:`register_model` (a name, a builder that makes an untrained
  :class:`~weathergen.models.base.FlowModel`, and the name of its default checkpoint), and
- its published checkpoints with :func:`register_checkpoint` (:class:`CheckpointSpec` data).

:func:`get_model` is the one entry point the rest of weathergen uses::

    model = get_model("raft", checkpoint="raft-things", iters=12)
    flow = model(image1, image2)

``name`` may also be a checkpoint name (``get_model("raft-kitti")``), which selects that
checkpoint's architecture, or a network from outside the package (:mod:`.external`):
``FILE.py:NAME``, ``package.module:NAME``, or the name of an entry point of the group
``weathergen.models``. A name is resolved once (:func:`resolve_network`) into a :class:`Network`
record, which the jobs carry and every function here takes in place of the name.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Union

import torch

from ..errors import ConfigError
from .base import PRECISIONS, FlowModel
from .checkpoints import CheckpointSpec, resolve_named
from .external import (build_external, declared_input, entry_points, is_adapter, is_external,
                       load_source, network_label, probe_network)

#: Builds an untrained adapter: ``build(iters=..., gradient_checkpointing=...)``.
Builder = Callable[..., FlowModel]


@dataclass(frozen=True)
class ModelSpec:
    """A registered architecture.

    Attributes:
        name: what users type (``raft``).
        build: makes an untrained, evaluation-mode adapter; keyword arguments ``iters`` (``None``
            for the network's default) and ``gradient_checkpointing``.
        default_checkpoint: the checkpoint name used when none is given.
        description: one line for listings.
        mixed_precision: the network has its authors' mixed-precision mode (CUDA autocast over
            the parts their code runs under it), which ``amp`` switches on.
        amp: the paper's configuration runs the network in mixed precision on CUDA: the
            default of ``--amp`` there (on the CPU mixed precision is always off).
        precision_bound: the largest RMS difference (pixels) from the float32 flow that a
            precision may make on the demo scene (``speed/bench_precision.py``, docs/models.md).
        refused_precisions: the precisions whose measured difference exceeds that bound.
    """

    name: str
    build: Builder
    default_checkpoint: Optional[str]
    description: str = ""
    mixed_precision: bool = False
    amp: bool = False
    precision_bound: float = 0.1
    refused_precisions: tuple = ()

    def __post_init__(self):
        if self.amp and not self.mixed_precision:
            raise ValueError(f"flow model {self.name!r}: amp by default needs mixed_precision")


_ARCHITECTURES: dict[str, ModelSpec] = {}
_CHECKPOINTS: dict[str, CheckpointSpec] = {}


def register_model(spec: ModelSpec) -> ModelSpec:
    """Add an architecture; a second registration under the same name is a bug."""
    if spec.name in _ARCHITECTURES:
        raise ValueError(f"flow model {spec.name!r} is registered twice")
    _ARCHITECTURES[spec.name] = spec
    return spec


def register_checkpoint(spec: CheckpointSpec) -> CheckpointSpec:
    """Add a named checkpoint; a second registration under the same name is a bug."""
    if spec.name in _CHECKPOINTS:
        raise ValueError(f"checkpoint {spec.name!r} is registered twice")
    _CHECKPOINTS[spec.name] = spec
    return spec


def available_models() -> list[str]:
    """Registered architecture names, sorted."""
    return sorted(_ARCHITECTURES)


def available_checkpoints(architecture: Optional[str] = None) -> list[str]:
    """Registered checkpoint names, sorted; only those fitting ``architecture`` if given."""
    return sorted(n for n, s in _CHECKPOINTS.items()
                  if architecture is None or s.architecture == architecture)


def model_spec(name: str) -> ModelSpec:
    """The registered architecture called ``name``.

    Raises:
        ConfigError: unknown name; the message lists the known ones.
    """
    if name in _ARCHITECTURES:
        return _ARCHITECTURES[name]
    raise ConfigError(_unknown_message(name))


@dataclass(frozen=True)
class Network:
    """A flow network resolved once from its name (:func:`resolve_network`), which the jobs
    carry and :func:`get_model` builds, so that a network of your own is read once per run.

    ``name``: as a manifest records it (a file network as ``PATH:NAME``, the path resolved);
    ``kind``: ``registered``, ``file``, ``module`` or ``entry-point``; ``label``: short, for
    folders and tables (``stem.NAME``); ``architecture`` and ``default_checkpoint``: of a
    registered one; ``attribute`` … ``distribution``: where a network of your own comes from
    (``sha256`` of the file that defines NAME); ``input``: a plain module's input convention (a
    key of :data:`~weathergen.models.external.INPUT_CONVENTIONS`; None for an adapter, which
    normalises itself), ``declared`` False where it is assumed.
    """

    name: str
    kind: str
    label: str
    architecture: Optional[str] = None
    default_checkpoint: Optional[str] = None
    attribute: Optional[str] = None
    path: Optional[str] = None
    module: Optional[str] = None
    sha256: Optional[str] = None
    entry_point: Optional[str] = None
    distribution: Optional[str] = None
    input: Optional[str] = None
    declared: bool = True
    mixed_precision: bool = False
    amp: bool = False

    @property
    def external(self) -> bool:
        """A network from outside the package."""
        return self.kind != "registered"

    def source(self) -> Optional[dict]:
        """What identifies a network of your own in a manifest (its code's file and sha256, its
        input convention); None for a registered one."""
        if not self.external:
            return None
        record = {k: getattr(self, k) for k in ("kind", "path", "module", "attribute", "sha256",
                                                "entry_point", "distribution")}
        return record if self.input is None else {**record, "input": self.input}

    def note(self) -> Optional[str]:
        """One line for a plain module that declares no input convention, else None."""
        if self.declared:
            return None
        return (f"flow model {self.label!r} declares no input convention: its frames are given "
                f"as RGB in [0, 1] (to say otherwise: its input_range and "
                f"channel_order, or --model-input; docs/models.md)")


def resolve_network(name, model_input: Optional[str] = None) -> Network:
    """The :class:`Network` a name means (a :class:`Network` is returned as it is), its code
    loaded here, once. ``model_input``: the input convention of a plain module that declares
    none. ConfigError: an unknown name, code that does not load, a bad or conflicting input
    convention."""
    if isinstance(name, Network):
        return name
    name = str(name)
    if name in _ARCHITECTURES or name in _CHECKPOINTS:
        if model_input is not None:
            raise ConfigError(f"${{model_input}} applies to a plain module of your own; {name!r} "
                              f"is weathergen's own and takes RGB in [0, 1]")
        arch = name if name in _ARCHITECTURES else _CHECKPOINTS[name].architecture
        spec = _ARCHITECTURES[arch]
        return Network(name, "registered", name, arch,
                       spec.default_checkpoint if name == arch else name,
                       mixed_precision=spec.mixed_precision, amp=spec.amp)
    if not is_external(name) and name not in entry_points():
        raise ConfigError(_unknown_message(name))
    fields, target = load_source(name)
    declared = None if is_adapter(target) else declared_input(target, name)
    if model_input is not None and (is_adapter(target) or declared not in (None, model_input)):
        raise ConfigError(f"${{model_input}} {model_input}: {name!r} declares "
                          f"{'its own normalisation' if declared is None else declared}")
    convention = None if is_adapter(target) else (declared or model_input or "rgb")
    return Network(**fields, label=network_label(name), input=convention,
                   declared=convention is None or declared is not None or model_input is not None,
                   mixed_precision=bool(target.supports_amp) if is_adapter(target) else True)


def renamed(error: ConfigError, parameter: str) -> ConfigError:
    """``error`` with ``${model}`` written as ``${parameter}``."""
    return ConfigError(error.args[0].replace("${model}", f"${{{parameter}}}"))


def checkpoint_spec(name: str) -> CheckpointSpec:
    """The registered checkpoint called ``name`` (``ConfigError`` listing the known ones)."""
    try:
        return _CHECKPOINTS[name]
    except KeyError:
        raise ConfigError(f"unknown checkpoint {name!r}; known checkpoints: "
                          f"{', '.join(available_checkpoints())}") from None


def resolve_amp(name, requested: Optional[bool], device: Union[str, torch.device, None]) -> bool:
    """Whether network ``name`` (a name or a :class:`Network`) runs in mixed precision.

    ``requested``: ``True``/``False`` as asked (``--amp``/``--no-amp``), ``None`` for the paper's
    configuration of the network (:attr:`ModelSpec.amp`). Mixed precision is CUDA autocast, so on
    any other device the answer is ``False``.

    Raises:
        ConfigError: ``requested`` is ``True`` on a device other than CUDA, or for a network
            without a mixed-precision mode; an unknown name.
    """
    network = resolve_network(name)
    try:
        kind = torch.device(device).type if device is not None else "cpu"
    except (RuntimeError, TypeError):
        raise ConfigError(f"invalid device {device!r}") from None
    if kind != "cuda":
        if requested:
            raise ConfigError(f"${{amp}} needs a CUDA device: mixed precision is CUDA autocast "
                              f"(device {device or 'cpu'}; leave it out, mixed precision is off "
                              f"there)")
        return False
    if requested and not network.mixed_precision:
        with_mode = [n for n in available_models() if _ARCHITECTURES[n].mixed_precision]
        raise ConfigError(f"${{amp}}: {network.architecture or network.name!r} has no "
                          f"mixed-precision mode (the paper ran it in float32); networks with "
                          f"one: {', '.join(with_mode)} and networks from outside the package "
                          f"(their own FlowModel's supports_amp, or any plain module)")
    return network.amp if requested is None else bool(requested)


def resolve_precision(name, precision: Optional[str], amp: Optional[bool],
                      device: Union[str, torch.device, None]) -> str:
    """The precision network ``name`` (a name or a :class:`Network`) runs in (one of
    :data:`~weathergen.models.base.PRECISIONS`).

    ``precision`` as asked (``--precision``), or None for ``amp``'s answer (:func:`resolve_amp`:
    ``fp16`` where mixed precision is on, else ``float32``).

    Raises:
        ConfigError: both given; an unknown precision; ``tf32`` off CUDA; a precision refused
            for the network (its flow differs from float32's by more than its bound); what
            :func:`resolve_amp` refuses.
    """
    if precision is None:
        return "fp16" if resolve_amp(name, amp, device) else "float32"
    if amp is not None:
        raise ConfigError("${precision} and ${amp} are exclusive: give one (--amp is the authors' "
                          "fp16 autocast on CUDA)")
    if precision not in PRECISIONS:
        raise ConfigError(f"${{precision}} must be one of {', '.join(PRECISIONS)}, got {precision!r}")
    network = resolve_network(name)
    kind = torch.device(device).type if device is not None else "cpu"
    if precision == "tf32" and kind != "cuda":
        raise ConfigError(f"${{precision}} tf32 needs a CUDA device (device {device or 'cpu'})")
    spec = None if network.external else _ARCHITECTURES[network.architecture]
    if spec is not None and precision in spec.refused_precisions:
        raise ConfigError(f"${{precision}} {precision} is refused for {spec.name!r}: its flow differs "
                          f"from float32's by more than its bound, {spec.precision_bound:g} px RMS "
                          f"(docs/models.md)")
    return precision


def build_model(name, iters: Optional[int] = None,
                gradient_checkpointing: bool = False) -> FlowModel:
    """An untrained (randomly initialised) adapter of network ``name`` (a name or a
    :class:`Network`; a network of your own with the weights its code gives it), in eval mode."""
    if iters is not None and (isinstance(iters, bool) or not isinstance(iters, int) or iters < 1):
        raise ConfigError(f"iters must be a positive integer, got {iters!r}")
    network = resolve_network(name)
    if network.external:
        return build_external(network, iters, gradient_checkpointing)
    return _ARCHITECTURES[network.architecture].build(
        iters=iters, gradient_checkpointing=gradient_checkpointing).eval()


def get_model(name, checkpoint: Union[str, Path, None] = None,
              device: Union[str, torch.device] = "cpu", iters: Optional[int] = None, *,
              download: bool = False, gradient_checkpointing: bool = False,
              timeout: float = 60.0, amp: bool = False,
              precision: Optional[str] = None) -> FlowModel:
    """A flow network with trained weights, ready to call as ``model(image1, image2)``.

    Args:
        name: an architecture (``raft``, ``raft-small``), a checkpoint name (``raft-kitti``), a
            network of your own (``FILE.py:NAME``, ``module:NAME``, an entry point), or its
            :class:`Network` (:func:`resolve_network`).
        checkpoint: a checkpoint name, a file path (an adapter may take a folder: SpyNet's
            per-level files), or ``None`` for the default of ``name``.
        device: where the model runs (``"cpu"``, ``"cuda"``, ``"cuda:1"``...).
        iters: refinement iterations for recurrent networks; ``None`` for the default.
        download: fetch a named checkpoint missing from the cache (needs a network).
        gradient_checkpointing: recompute activations in the backward pass instead of
            keeping them (less memory for attacks, more time).
        timeout: seconds a download may stall before it is given up.
        amp: run the network in its authors' mixed precision (fp16 autocast; see
            :func:`resolve_amp` for the paper's setting per network).
        precision: one of :data:`~weathergen.models.base.PRECISIONS` (checked by
            :func:`resolve_precision`), instead of ``amp``.

    The returned model is in evaluation mode and its parameters do not require gradients;
    gradients still flow to the input images. A network of your own is run once on a small
    random pair (:func:`~weathergen.models.external.probe_network`).

    Raises:
        ConfigError: unknown name or checkpoint, a checkpoint for another architecture, a
            missing file (the message says which file to put where), an unusable device.
        FormatError: the checkpoint file is unreadable or does not fit the architecture.
        ShapeError: a network of your own answers a flow of another shape.
    """
    network = resolve_network(name)
    if precision is not None:       # checked before any weights are read
        precision = resolve_precision(network, precision, None, device)
    checkpoint = network.default_checkpoint if checkpoint is None else checkpoint
    if amp and not network.mixed_precision:
        raise ConfigError(f"${{amp}}: {network.architecture or network.name!r} has no "
                          f"mixed-precision mode")
    if checkpoint is None and not network.external:
        raise ConfigError(f"flow model {network.architecture!r} has no default checkpoint; give "
                          f"one by path")
    device = _device(device)
    path, what = (None, None) if checkpoint is None else _resolve_checkpoint(
        network, checkpoint, download, timeout)
    model = build_model(network, iters=iters, gradient_checkpointing=gradient_checkpointing)
    model.amp = bool(amp)
    if path is not None:
        model.load_checkpoint(model.read_checkpoint(path), source=path, what=what)
    model.requires_grad_(False)
    model = _in_precision(model.to(device).eval(), precision)
    if network.external:
        probe_network(model, network.label)
    return model


def _in_precision(model: FlowModel, precision: Optional[str]) -> FlowModel:
    """``model`` set to run in ``precision`` where one is given. TF32 is switched on for the
    process, so that the backward passes (outside the network's forward) run in it too."""
    if precision == "tf32":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    if precision is not None:
        model.precision = precision
    return model


def _resolve_checkpoint(network: Network, checkpoint: Union[str, Path], download: bool,
                        timeout: float) -> tuple[Path, str]:
    arch = network.architecture
    if network.external:
        path = Path(checkpoint).expanduser()
        if not path.exists():
            raise ConfigError(f"checkpoint {str(checkpoint)!r}: no such file (a network from "
                              f"outside the package takes a checkpoint file, or none)")
        return path, repr(network.name)
    if isinstance(checkpoint, str) and checkpoint in _CHECKPOINTS:
        spec = _CHECKPOINTS[checkpoint]
        if spec.architecture != arch:
            raise ConfigError(f"checkpoint {checkpoint!r} is for {spec.architecture!r}, not "
                              f"{arch!r}; checkpoints for {arch!r}: "
                              f"{', '.join(available_checkpoints(arch)) or 'none'}")
        return resolve_named(spec, download=download, timeout=timeout), arch
    path = Path(checkpoint).expanduser()
    if not path.exists():   # a folder is for the adapter to judge (SpyNet's per-level files)
        raise ConfigError(f"checkpoint {str(checkpoint)!r} is neither a file nor a known "
                          f"checkpoint name ({', '.join(available_checkpoints(arch))})")
    return path, arch


def _device(device: Union[str, torch.device]) -> torch.device:
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ConfigError(f"invalid device {device!r} ({exc})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {device!r} requested but CUDA is not available here")
    return dev


def _unknown_message(name: str) -> str:
    if str(name).endswith(".py"):
        return f"flow model {name!r}: a network in a file is named FILE.py:NAME, NAME what it defines"
    installed = sorted(n for n in entry_points() if n not in _ARCHITECTURES and n not in _CHECKPOINTS)
    extra = f"; installed networks: {', '.join(installed)}" if installed else ""
    return (f"unknown flow model {name!r}; known models: {', '.join(available_models())}; "
            f"known checkpoints: {', '.join(available_checkpoints())}{extra}; or a network of "
            f"your own as FILE.py:NAME or package.module:NAME")

