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

import torch
from torch import nn

from ..errors import ShapeError
from .checkpoints import load_strict, read_state_dict
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
    #: Whether the network has its authors' mixed-precision mode (see :attr:`amp`).
    supports_amp: bool = False
    #: Run the parts its authors' code runs under CUDA autocast in float16 (``mixed_precision``
    #: of RAFT's and GMA's code). Only CUDA tensors are affected; elsewhere it changes nothing.
    amp: bool = False

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
        flow = self.predict(x1, x2)
        _check_flow(flow, (image1.shape[0], 2, *padder.padded_size), self)
        return padder.unpad(flow).to(image1.dtype)


def mixed_precision(enabled: bool):
    """CUDA autocast (float16) where ``enabled``, else nothing: the regions of the networks that
    their authors' code runs under ``torch.cuda.amp.autocast(enabled=mixed_precision)``. As
    there, tensors on other devices are not affected."""
    return torch.autocast("cuda", dtype=torch.float16) if enabled else contextlib.nullcontext()


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
