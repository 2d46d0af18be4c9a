"""The contract every flow network in weathergen keeps.

A :class:`FlowModel` takes two frames in the package's image convention and returns the flow from
the first to the second in the package's flow convention, at the input resolution::

    flow = model(image1, image2)

Everything network-specific (value range, channel order, padding to a multiple, upsampling of
the prediction) happens inside the adapter, so the attack and the evaluation never need to know
which network they talk to. The adapter is differentiable with respect to both images: the attack
backpropagates a loss on the flow into the weather particles that were rendered into them.
"""

from __future__ import annotations

import contextlib
import functools
from typing import Optional

import torch
from torch import nn

from ..errors import ShapeError
from .checkpoints import load_strict, read_state_dict, strip_prefix
from .padding import InputPadder


class FlowModel(nn.Module):
    """Base class of the flow-network adapters.

    Subclasses set :attr:`multiple` and :attr:`min_size` (padding requirements) and implement
    :meth:`normalize` and :meth:`predict`; :meth:`forward` checks the inputs, pads, normalises,
    predicts and crops.

    Shape:
        image1, image2: ``(B, 3, H, W)`` RGB float in ``[0, 1]``, any ``H``, ``W``.
        returns: ``(B, 2, H, W)`` flow in pixels from frame 1 to frame 2 (``u`` right, ``v`` down).
    """

    #: Name under which the architecture is registered (set by subclasses).
    architecture: str = ""
    #: The network sees only sizes that are a multiple of this.
    multiple: int = 1
    #: The network needs at least this many rows and columns (after padding).
    min_size: int = 0
    #: Where padding rows go: "even" or "bottom" (KITTI's protocol); set from ``Dataset.padding``.
    padding: str = "even"
    #: Whether the network has its authors' mixed-precision mode (see :attr:`amp`): the adapter
    #: places its own autocast regions (RAFT's and GMA's ``mixed_precision``); any other network
    #: runs its whole :meth:`predict` under autocast, less its float32 parts (:func:`in_float32`).
    supports_amp: bool = False
    #: One of :data:`PRECISIONS`: ``float32``; ``tf32`` (matrix products and convolutions on
    #: CUDA tensor cores in TF32); ``bf16``, ``fp16`` (autocast on the frames' device).
    precision: str = "float32"

    @property
    def amp(self) -> bool:
        """Whether the network runs under autocast (``bf16`` or ``fp16``); setting it chooses
        ``fp16`` (the authors' mixed precision) or ``float32``."""
        return self.precision in AUTOCAST

    @amp.setter
    def amp(self, on: bool) -> None:
        self.precision = "fp16" if on else "float32"

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        """Turn ``(B, 3, H, W)`` RGB in ``[0, 1]`` into what the network was trained on."""
        raise NotImplementedError

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        """Flow ``(B, 2, H, W)`` in pixels for normalised, padded frames ``(B, 3, H, W)``."""
        raise NotImplementedError

    def read_checkpoint(self, path) -> dict:
        """The state dict a checkpoint path holds (a file saved with ``torch.save``).

        Adapters whose authors published weights in other forms (several files, another
        framework's format) override this.

        Raises:
            FormatError: naming the file that cannot be read.
        """
        return read_state_dict(path)

    def load_checkpoint(self, state_dict: dict, source, what: str) -> None:
        """Load a published ``state_dict`` strictly (names and shapes must match).

        Adapters override this to translate the key layout of their authors' files.

        Raises:
            FormatError: naming ``source`` and listing what did not match.
        """
        load_strict(self, state_dict, source, what)

    def padder(self, height: int, width: int) -> InputPadder:
        """The padder this network uses for frames of ``height`` x ``width`` pixels."""
        return InputPadder(height, width, multiple=self.multiple, min_size=self.min_size,
                           placement=self.padding)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        _check_images(image1, image2)
        # Run in the weights' precision (float64 images into a float32 network, or the reverse
        # for a float64 gradient check) and answer in the images' precision.
        weights = next(self.parameters(), None)
        dtype = image1.dtype if weights is None else weights.dtype
        padder = self.padder(image1.shape[-2], image1.shape[-1])
        x1 = self.normalize(padder.pad(image1.to(dtype)))
        x2 = self.normalize(padder.pad(image2.to(dtype)))
        with _tf32(self.precision == "tf32"), mixed_precision(
                None if self.supports_amp else autocast_mode(self.precision, x1)):
            flow = self.predict(x1, x2)
        _check_flow(flow, (image1.shape[0], 2, *padder.padded_size), self)
        return padder.unpad(flow).to(image1.dtype)


class IteratedFlowModel(FlowModel):
    """What the adapters of RAFT, GMA and FlowFormer share: a network run for ``iters``
    refinement steps on RAFT's input range, optionally with gradient checkpointing, loaded from
    its authors' files as they are (with or without the ``module.`` prefix that saving from
    ``DataParallel`` adds).
    Subclasses set :attr:`network` and :attr:`iters` (see :meth:`_setup`)."""

    def _setup(self, network: nn.Module, iters: Optional[int], default_iters: int,
               gradient_checkpointing: bool, detach_flow: bool) -> None:
        self.network = network
        self.iters = default_iters if iters is None else int(iters)
        self.gradient_checkpointing = gradient_checkpointing
        self.detach_flow = detach_flow

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        # The released models were trained on 2 * (pixel / 255) - 1.
        return 2.0 * image - 1.0

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        kwargs = {"amp": self.precision} if self.supports_amp else {}
        return self.network(image1, image2, iters=self.iters, detach_flow=self.detach_flow,
                            gradient_checkpointing=self.gradient_checkpointing, **kwargs)

    def load_checkpoint(self, state_dict: dict, source, what: str) -> None:
        """Load a file of the authors' release, with or without the ``module.`` prefix."""
        load_strict(self.network, strip_prefix(state_dict, "module."), source, what)

    def extra_repr(self) -> str:
        return f"iters={self.iters}, gradient_checkpointing={self.gradient_checkpointing}"


#: The precisions a network may run in (``--precision``); the last two are autocast's.
PRECISIONS = ("float32", "tf32", "bf16", "fp16")
#: Autocast's precisions and their dtypes.
AUTOCAST = {"bf16": torch.bfloat16, "fp16": torch.float16}


def autocast_mode(precision, like: torch.Tensor) -> Optional[tuple]:
    """``(device type, dtype)`` of the autocast a ``precision`` (a name of :data:`PRECISIONS`;
    ``True``: ``fp16``, the authors' mixed precision) asks for on the device of ``like``; None
    for none (float32, tf32, False)."""
    dtype = AUTOCAST.get("fp16" if precision is True else precision)
    return None if dtype is None else (like.device.type, dtype)


def mixed_precision(mode: Optional[tuple]):
    """Autocast in ``mode`` (:func:`autocast_mode`), else nothing: the regions of the networks
    that their authors' code runs under ``autocast(enabled=mixed_precision)``."""
    return torch.autocast(mode[0], dtype=mode[1]) if mode else contextlib.nullcontext()


@contextlib.contextmanager
def _tf32(enabled: bool):
    """CUDA matrix products and cuDNN convolutions in TF32 while ``enabled`` (restored after)."""
    if not enabled:
        yield
        return
    saved = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = True
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


def in_float32(fn):
    """``fn`` run in float32 whatever autocast is on: its half-precision tensor arguments taken
    to float32, autocast off on their device (a network's correlation volume, its softmax, its
    warping). Float64 arguments (gradient checks) stay float64."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        tensors = [a for a in args if isinstance(a, torch.Tensor)]
        args = [a.float() if isinstance(a, torch.Tensor) and a.dtype in AUTOCAST.values() else a
                for a in args]
        with torch.autocast(tensors[0].device.type if tensors else "cpu", enabled=False):
            return fn(*args, **kwargs)
    return run


def _check_images(image1: torch.Tensor, image2: torch.Tensor) -> None:
    for name, image in (("image1", image1), ("image2", image2)):
        if not isinstance(image, torch.Tensor):
            raise TypeError(f"expected {name} to be a torch.Tensor, got {type(image).__name__}")
        if image.dim() != 4 or image.shape[1] != 3:
            raise ShapeError(f"expected {name} of shape (B, 3, H, W), got {tuple(image.shape)}")
        if not image.is_floating_point():
            raise ShapeError(f"expected {name} to be a float tensor in [0, 1], got {image.dtype}")
    if image1.shape != image2.shape:
        raise ShapeError(f"expected image1 and image2 of the same shape, got "
                         f"{tuple(image1.shape)} and {tuple(image2.shape)}")


def _check_flow(flow, expected: tuple, model: FlowModel) -> None:
    """The prediction must be a flow tensor of the padded frames' shape; ShapeError naming the
    network otherwise."""
    name = model.architecture or type(model).__name__
    if not isinstance(flow, torch.Tensor):
        raise ShapeError(f"flow model {name!r} returned a value of type {type(flow).__name__}, "
                         f"expected a flow tensor of shape {expected}")
    if tuple(flow.shape) != tuple(expected):
        raise ShapeError(f"flow model {name!r} returned a flow of shape {tuple(flow.shape)} for "
                         f"frames of shape ({expected[0]}, 3, {expected[2]}, {expected[3]}), "
                         f"expected {tuple(expected)}")
