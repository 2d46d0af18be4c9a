"""Padding frames to the size a flow network needs, and taking the padding off its output again.

Most flow networks downsample by a fixed factor (RAFT by 8) and so accept only sizes that are a
multiple of it. :class:`InputPadder` records, for one frame size, how many rows and columns to add
on each side, so that the same object pads both frames and crops the predicted flow back to the
input size. Padding replicates the border pixels (a constant border would be an edge the
network sees as structure); it is built from differentiable tensor operations.

Where the rows go follows the benchmark's evaluation protocol (``placement``): on Sintel (and by
default) they are split evenly between top and bottom; on KITTI they all go to the bottom, as in
the published KITTI evaluation of RAFT and its successors, so that EPE figures compare. Columns are
split evenly in both. A dataset reader names its protocol in ``Dataset.padding``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from ..errors import ShapeError


#: Where the extra rows go: "even" (top and bottom, Sintel's protocol) or "bottom" (KITTI's).
PLACEMENTS = ("even", "bottom")


class InputPadder:
    """Pads ``(..., H, W)`` tensors to a multiple of ``multiple`` and crops them back.

    The extra columns are split evenly between left and right (one more at the right when the
    count is odd); the extra rows likewise between top and bottom with ``placement="even"``, or
    all at the bottom with ``placement="bottom"``. ``min_size`` raises the padded size further where a network
    needs a minimum extent (e.g. enough pixels for every level of a pyramid).

    Shape:
        pad: ``(..., H, W)`` -> ``(..., H + top + bottom, W + left + right)``.
        unpad: ``(..., H_padded, W_padded)`` -> ``(..., H, W)``.
    """

    def __init__(self, height: int, width: int, multiple: int = 8, min_size: int = 0,
                 mode: str = "replicate", placement: str = "even"):
        if height < 1 or width < 1:
            raise ValueError(f"expected a positive frame size, got {height}x{width}")
        if multiple < 1:
            raise ValueError(f"expected a positive padding multiple, got {multiple}")
        if placement not in PLACEMENTS:
            raise ValueError(f"padding placement must be one of {', '.join(PLACEMENTS)}, got {placement!r}")
        self.placement = placement
        self.height, self.width = int(height), int(width)
        self.multiple = int(multiple)
        self.mode = mode
        padded_h = self._target(self.height, min_size)
        padded_w = self._target(self.width, min_size)
        extra_h, extra_w = padded_h - self.height, padded_w - self.width
        self.top = extra_h // 2 if placement == "even" else 0
        self.bottom = extra_h - self.top
        self.left, self.right = extra_w // 2, extra_w - extra_w // 2

    def _target(self, size: int, min_size: int) -> int:
        size = max(size, min_size)
        return -(-size // self.multiple) * self.multiple  # round up to the multiple

    @property
    def padded_size(self) -> tuple[int, int]:
        """``(H, W)`` after padding."""
        return (self.height + self.top + self.bottom, self.width + self.left + self.right)

    def pad(self, x: torch.Tensor) -> torch.Tensor:
        """Pad a ``(B, C, H, W)`` tensor of the size this padder was made for."""
        if tuple(x.shape[-2:]) != (self.height, self.width):
            raise ShapeError(f"expected a tensor of size {self.height}x{self.width}, "
                             f"got {x.shape[-2]}x{x.shape[-1]}")
        if not (self.top or self.bottom or self.left or self.right):
            return x
        # F.pad's order is (left, right, top, bottom) for the last two dimensions.
        return F.pad(x, (self.left, self.right, self.top, self.bottom), mode=self.mode)

    def unpad(self, x: torch.Tensor) -> torch.Tensor:
        """Crop a padded ``(..., H_padded, W_padded)`` tensor back to ``(..., H, W)``."""
        if tuple(x.shape[-2:]) != self.padded_size:
            raise ShapeError(f"expected a tensor of padded size {self.padded_size[0]}x"
                             f"{self.padded_size[1]}, got {x.shape[-2]}x{x.shape[-1]}")
        return x[..., self.top:self.top + self.height, self.left:self.left + self.width]

    def __repr__(self) -> str:
        return (f"InputPadder({self.height}x{self.width} -> {self.padded_size[0]}x"
                f"{self.padded_size[1]}, top={self.top}, bottom={self.bottom}, "
                f"left={self.left}, right={self.right})")
