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
``weathergen.models``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Union

import torch

from ..errors import ConfigError
from .base import PRECISIONS, FlowModel
from .checkpoints import CheckpointSpec, resolve_named
from .external import (check_network, entry_point, entry_points, external_network, is_external,
                       network_source, spec_label, supports_amp)

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


_MODELS: dict[str, ModelSpec] = {}
_CHECKPOINTS: dict[str, CheckpointSpec] = {}


def register_model(spec: ModelSpec) -> ModelSpec:
    """Add an architecture; a second registration under the same name is a bug."""
    if spec.name in _MODELS:
        raise ValueError(f"flow model {spec.name!r} is registered twice")
    _MODELS[spec.name] = spec
    return spec


def register_checkpoint(spec: CheckpointSpec) -> CheckpointSpec:
    """Add a named checkpoint; a second registration under the same name is a bug."""
    if spec.name in _CHECKPOINTS:
        raise ValueError(f"checkpoint {spec.name!r} is registered twice")
    _CHECKPOINTS[spec.name] = spec
    return spec


def available_models() -> list[str]:
    """Registered architecture names, sorted."""
    return sorted(_MODELS)


def available_checkpoints(architecture: Optional[str] = None) -> list[str]:
    """Registered checkpoint names, sorted; only those fitting ``architecture`` if given."""
    return sorted(n for n, s in _CHECKPOINTS.items()
                  if architecture is None or s.architecture == architecture)


def model_spec(name: str) -> ModelSpec:
    """The registered architecture called ``name``.

    Raises:
        ConfigError: unknown name; the message lists the known ones.
    """
    if name in _MODELS:
        return _MODELS[name]
    if is_external_name(name):
        return _external_spec(name)
    raise ConfigError(_unknown_message(name))


def is_external_name(name) -> bool:
    """Whether ``name`` names a network from outside the package: ``FILE.py:NAME``,
    ``module:NAME``, or an entry point of ``weathergen.models`` that no registered architecture
    or checkpoint shadows."""
    if is_external(name):
        return True
    return (isinstance(name, str) and name not in _MODELS and name not in _CHECKPOINTS
            and entry_point(name) is not None)


def _external_spec(name: str) -> ModelSpec:
    """The :class:`ModelSpec` of an external network (loads its code)."""
    def build(iters=None, gradient_checkpointing=False):
        return external_network(name, iters=iters, gradient_checkpointing=gradient_checkpointing)

    source = network_source(name)
    return ModelSpec(name=str(name), build=build, default_checkpoint=None,
                     description=f"{source.kind} {source.canonical}",
                     mixed_precision=supports_amp(name))


def network_record(name: str) -> Optional[dict]:
    """What identifies an external network's code in a manifest (its file and the file's sha256,
    see :meth:`~weathergen.models.external.NetworkSource.record`); None for a registered one."""
    return network_source(name).record() if is_external_name(name) else None


def canonical_network(name: str) -> str:
    """``name`` as a manifest records it: a file network by its resolved path (the same from any
    working directory), every other name as given."""
    return network_source(name).canonical if is_external_name(name) else str(name)


def network_label(name: str) -> str:
    """A short name of the network fit for a file or folder name and a table column: the
    registered name, ``stem.NAME`` of a file network, ``module.NAME``, an entry point's name
    (from the name alone: nothing is loaded)."""
    return spec_label(name)


def checkpoint_spec(name: str) -> CheckpointSpec:
    """The registered checkpoint called ``name`` (``ConfigError`` listing the known ones)."""
    try:
        return _CHECKPOINTS[name]
    except KeyError:
        raise ConfigError(f"unknown checkpoint {name!r}; known checkpoints: "
                          f"{', '.join(available_checkpoints())}") from None


def resolve_amp(name: str, requested: Optional[bool],
                device: Union[str, torch.device, None]) -> bool:
    """Whether network ``name`` (an architecture or a checkpoint name) runs in mixed precision.

    ``requested``: ``True``/``False`` as asked (``--amp``/``--no-amp``), ``None`` for the paper's
    configuration of the network (:attr:`ModelSpec.amp`). Mixed precision is CUDA autocast, so on
    any other device the answer is ``False``.

    Raises:
        ConfigError: ``requested`` is ``True`` on a device other than CUDA, or for a network
            without a mixed-precision mode; an unknown name.
    """
    spec = model_spec(name if is_external_name(name) else _architecture_of(name))
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
    if requested and not spec.mixed_precision:
        raise ConfigError(f"${{amp}}: {spec.name!r} has no mixed-precision mode (the paper ran it "
                          f"in float32); networks with one: "
                          f"{', '.join(n for n in available_models() if _MODELS[n].mixed_precision)}"
                          f" and networks from outside the package (their own FlowModel's "
                          f"supports_amp, or any plain module)")
    return spec.amp if requested is None else bool(requested)


def resolve_precision(name: str, precision: Optional[str], amp: Optional[bool],
                      device: Union[str, torch.device, None]) -> str:
    """The precision network ``name`` runs in (one of :data:`~weathergen.models.base.PRECISIONS`).

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
    spec = model_spec(name if is_external_name(name) else _architecture_of(name))
    kind = torch.device(device).type if device is not None else "cpu"
    if precision == "tf32" and kind != "cuda":
        raise ConfigError(f"${{precision}} tf32 needs a CUDA device (device {device or 'cpu'})")
    if precision in spec.refused_precisions:
        raise ConfigError(f"${{precision}} {precision} is refused for {spec.name!r}: its flow differs "
                          f"from float32's by more than its bound, {spec.precision_bound:g} px RMS "
                          f"(docs/models.md)")
    return precision


def _architecture_of(name: str) -> str:
    if name in _MODELS:
        return name
    if name in _CHECKPOINTS:
        return _CHECKPOINTS[name].architecture
    raise ConfigError(_unknown_message(name))


def build_model(name: str, iters: Optional[int] = None,
                gradient_checkpointing: bool = False) -> FlowModel:
    """An untrained (randomly initialised) adapter of architecture ``name``, in eval mode."""
    if iters is not None and (isinstance(iters, bool) or not isinstance(iters, int) or iters < 1):
        raise ConfigError(f"iters must be a positive integer, got {iters!r}")
    model = model_spec(name).build(iters=iters, gradient_checkpointing=gradient_checkpointing)
    return model.eval()


def get_model(name: str, checkpoint: Union[str, Path, None] = None,
              device: Union[str, torch.device] = "cpu", iters: Optional[int] = None, *,
              download: bool = False, gradient_checkpointing: bool = False,
              timeout: float = 60.0, amp: bool = False,
              precision: Optional[str] = None) -> FlowModel:
    """A flow network with trained weights, ready to call as ``model(image1, image2)``.

    Args:
        name: an architecture (``raft``, ``raft-small``) or a checkpoint name (``raft-kitti``).
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
    gradients still flow to the input images.

    Raises:
        ConfigError: unknown name or checkpoint, a checkpoint for another architecture, a
            missing file (the message says which file to put where), an unusable device.
        FormatError: the checkpoint file is unreadable or does not fit the architecture.
    """
    if precision is not None:       # checked before any weights are read
        precision = resolve_precision(name, precision, None, device)
    if name not in _MODELS and name not in _CHECKPOINTS and is_external_name(name):
        model = _get_external(name, checkpoint, device, iters, gradient_checkpointing, amp)
        return _in_precision(model, precision)
    if name in _MODELS:
        arch = name
        if checkpoint is None:
            checkpoint = _MODELS[name].default_checkpoint
    elif name in _CHECKPOINTS:
        arch = _CHECKPOINTS[name].architecture
        if checkpoint is None:
            checkpoint = name
    else:
        raise ConfigError(_unknown_message(name))
    if checkpoint is None:
        raise ConfigError(f"flow model {arch!r} has no default checkpoint; give one by path")

    if amp and not _MODELS[arch].mixed_precision:
        raise ConfigError(f"${{amp}}: {arch!r} has no mixed-precision mode")
    path, what = _resolve_checkpoint(arch, checkpoint, download, timeout)
    device = _device(device)
    model = build_model(arch, iters=iters, gradient_checkpointing=gradient_checkpointing)
    model.amp = bool(amp)
    model.load_checkpoint(model.read_checkpoint(path), source=path, what=what)
    model.requires_grad_(False)
    return _in_precision(model.to(device).eval(), precision)


def _in_precision(model: FlowModel, precision: Optional[str]) -> FlowModel:
    """``model`` set to run in ``precision`` where one is given. TF32 is switched on for the
    process, so that the backward passes (outside the network's forward) run in it too."""
    if precision == "tf32":
        torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    if precision is not None:
        model.precision = precision
    return model


def _get_external(name: str, checkpoint, device, iters, gradient_checkpointing: bool,
                  amp: bool) -> FlowModel:
    """A network from outside the package: built by its own code (with the weights that code
    gives it), a checkpoint file loaded into it where one is given, checked on a small pair."""
    spec = _external_spec(name)
    if amp and not spec.mixed_precision:
        raise ConfigError(f"${{amp}}: {name!r} has no mixed-precision mode (its supports_amp is "
                          f"false)")
    device = _device(device)
    model = build_model(name, iters=iters, gradient_checkpointing=gradient_checkpointing)
    model.amp = bool(amp)
    if checkpoint is not None:
        path = Path(checkpoint).expanduser()
        if not path.exists():
            raise ConfigError(f"checkpoint {str(checkpoint)!r}: no such file (a network from "
                              f"outside the package takes a checkpoint file, or none)")
        model.load_checkpoint(model.read_checkpoint(path), source=path, what=repr(name))
    model.requires_grad_(False)
    model = model.to(device).eval()
    check_network(model, name, device)
    return model


def _resolve_checkpoint(arch: str, checkpoint: Union[str, Path], download: bool,
                        timeout: float) -> tuple[Path, str]:
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
    installed = sorted(n for n in entry_points() if n not in _MODELS and n not in _CHECKPOINTS)
    extra = f"; installed networks: {', '.join(installed)}" if installed else ""
    return (f"unknown flow model {name!r}; known models: {', '.join(available_models())}; "
            f"known checkpoints: {', '.join(available_checkpoints())}{extra}; or a network of "
            f"your own as FILE.py:NAME or package.module:NAME")

