"""SpyNet (Ranjan and Black, "Optical Flow Estimation using a Spatial Pyramid Network",
CVPR 2017).

A coarse-to-fine pyramid with one small CNN per level:

1. **Image pyramid**: both frames are averaged 2x2 repeatedly (up to 5 times, while the level
   is larger than 32 pixels in height or width), giving up to 6 levels.
2. **Per level, coarse to fine**: the flow of the coarser level is upsampled (bilinear,
   corner-aligned, values doubled), frame 2 is warped towards frame 1 with it, and the level's
   network (five 7x7 convolutions: 8 -> 32 -> 64 -> 32 -> 16 -> 2 channels, ReLU between)
   predicts a residual flow from frame 1, the warped frame 2 and the upsampled flow
   (3 + 3 + 2 channels). The coarsest level starts from zero flow.

The finest level's output is the flow in pixels at the input resolution.

Module and parameter names follow the Sintel-final checkpoint ``network-sintel-final.pytorch``
of the PyTorch port of SpyNet by Simon Niklaus (github.com/sniklaus/pytorch-spynet), whose
weights are converted from the authors' Torch release: ``moduleBasic.<level>.moduleBasic.<k>``
with level 0 the coarsest. Files saved from the port's current code, which names the same
modules ``netBasic``, load too.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from .base import FlowModel
from .checkpoints import CheckpointSpec, load_strict, strip_prefix
from .flownet_parts import warp
from .registry import ModelSpec, register_checkpoint, register_model

#: ImageNet statistics the released model normalises RGB in [0, 1] with.
RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)

#: Pyramid levels of the released models.
LEVELS = 6


class SpyNetLevel(nn.Module):
    """The network of one pyramid level.

    Shape: ``(B, 8, h, w)`` (frame 1, warped frame 2, upsampled flow) -> ``(B, 2, h, w)``.
    """

    def __init__(self):
        super().__init__()
        widths = (8, 32, 64, 32, 16, 2)
        layers: list[nn.Module] = []
        for i, (cin, cout) in enumerate(zip(widths[:-1], widths[1:])):
            if i:
                layers.append(nn.ReLU())
            layers.append(nn.Conv2d(cin, cout, 7, padding=3))
        self.moduleBasic = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.moduleBasic(x)


class SpyNet(nn.Module):
    """SpyNet on normalised frames.

    The pyramid has one level more for each halving while the current level is larger than
    32 pixels in height or width (at most ``levels - 1`` halvings); the networks of the
    coarsest levels are used, from level 0 on, so small frames use fewer of them. Sizes that
    are a multiple of 32 keep every level's size exact.

    Shape: ``image1``, ``image2`` ``(B, 3, H, W)`` -> ``(B, 2, H, W)`` flow in pixels.
    """

    def __init__(self, levels: int = LEVELS):
        super().__init__()
        self.moduleBasic = nn.ModuleList([SpyNetLevel() for _ in range(levels)])

    def forward(self, image1: torch.Tensor, image2: torch.Tensor,
                gradient_checkpointing: bool = False) -> torch.Tensor:
        """``gradient_checkpointing``: recompute each level in the backward pass."""
        pyramid = [(image1, image2)]
        for _ in range(len(self.moduleBasic) - 1):
            first, second = pyramid[0]
            if first.shape[-2] <= 32 and first.shape[-1] <= 32:
                break
            pyramid.insert(0, (F.avg_pool2d(first, 2), F.avg_pool2d(second, 2)))

        top = pyramid[0][0]
        flow = top.new_zeros(top.shape[0], 2, math.floor(top.shape[-2] / 2),
                             math.floor(top.shape[-1] / 2))
        use_recompute = gradient_checkpointing and torch.is_grad_enabled()
        for level, (first, second) in enumerate(pyramid):
            step = self.moduleBasic[level]
            if use_recompute:
                flow = recompute(_refine, step, first, second, flow, use_reentrant=False)
            else:
                flow = _refine(step, first, second, flow)
        return flow


def _refine(step: nn.Module, first: torch.Tensor, second: torch.Tensor,
            coarse_flow: torch.Tensor) -> torch.Tensor:
    """One pyramid level: upsample the coarser flow, warp, predict the residual."""
    up = 2.0 * F.interpolate(coarse_flow, scale_factor=2, mode="bilinear", align_corners=True)
    # An odd level size: the doubled coarse flow is one short; repeat its last row / column.
    if up.shape[-2] != first.shape[-2]:
        up = F.pad(up, (0, 0, 0, first.shape[-2] - up.shape[-2]), mode="replicate")
    if up.shape[-1] != first.shape[-1]:
        up = F.pad(up, (0, first.shape[-1] - up.shape[-1], 0, 0), mode="replicate")
    return step(torch.cat([first, warp(second, up), up], dim=1)) + up


class SpyNetModel(FlowModel):
    """SpyNet behind the package contract.

    Normalisation: RGB in ``[0, 1]``, minus the ImageNet mean, divided by the ImageNet standard
    deviation (per channel). Padding: to a multiple of 32 (border replicated; the port resizes
    instead, which rescales the flow). ``iters`` is ignored (not recurrent);
    ``gradient_checkpointing`` recomputes each pyramid level in the backward pass.
    """

    architecture = "spynet"
    multiple = 32
    min_size = 32

    def __init__(self, iters: Optional[int] = None, gradient_checkpointing: bool = False):
        super().__init__()
        self.network = SpyNet()
        self.gradient_checkpointing = gradient_checkpointing
        self.register_buffer("rgb_mean", torch.tensor(RGB_MEAN).view(1, 3, 1, 1),
                             persistent=False)
        self.register_buffer("rgb_std", torch.tensor(RGB_STD).view(1, 3, 1, 1),
                             persistent=False)

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        return (image - self.rgb_mean.to(image.dtype)) / self.rgb_std.to(image.dtype)

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        return self.network(image1, image2, gradient_checkpointing=self.gradient_checkpointing)

    def load_checkpoint(self, state_dict: dict, source, what: str) -> None:
        """Load the port's file (``moduleBasic.*``; ``netBasic.*`` is renamed), with or
        without ``module.``."""
        state_dict = strip_prefix(state_dict, "module.")
        if state_dict and all(k.startswith("netBasic.") for k in state_dict):
            state_dict = {k.replace("netBasic", "moduleBasic"): v for k, v in state_dict.items()}
        load_strict(self.network, state_dict, source, what)


#: Where the PyTorch port of SpyNet publishes its converted weights.
SPYNET_URL = "http://content.sniklaus.com/github/pytorch-spynet/network-{}.pytorch"

register_model(ModelSpec(
    name="spynet", build=SpyNetModel, default_checkpoint="spynet-sintel-final",
    description="SpyNet (Ranjan and Black, CVPR 2017), 1.4M parameters"))
for _variant in ("sintel-final", "sintel-clean", "chairs-final", "chairs-clean", "kitti-final"):
    register_checkpoint(CheckpointSpec(
        f"spynet-{_variant}", "spynet",
        f"SpyNet, the authors' {_variant} model (converted by the PyTorch port)",
        url=SPYNET_URL.format(_variant)))
