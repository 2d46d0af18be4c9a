"""FlowNetCRobust (Schrodi, Saikia and Brox, "Towards Understanding Adversarial Robustness of
Optical Flow Networks", CVPR 2022).

FlowNetC with a larger receptive field in its Siamese encoder: after each of the three strided
convolutions (7x7 to 64 channels, then 3x3 to 128 and 256 channels) come three more 3x3
convolutions of the same width, so that the features that are correlated see more context
(the authors found that this, not adversarial training, made FlowNetC far less sensitive to
adversarial patches). Correlation, second encoder part and refinement decoder are those of
FlowNetC (:mod:`weathergen.models.flownetc`), except that the decoder's transposed
convolutions have no bias. The authors trained it to predict flow in pixels at 1/4 resolution
(no factor 20); the adapter upsamples bilinearly by 4.

Module and parameter names follow the authors' released ``RobustFlowNetC.pth`` (a plain state
dict), so it loads as it is.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from .base import FlowModel
from .checkpoints import CheckpointSpec, load_strict, strip_prefix
from .flownet_parts import (LEAKY_SLOPE, RefinementDecoder, conv_block, correlation,
                            init_flownet_weights, upsample_bilinear)
from .registry import ModelSpec, register_checkpoint, register_model

#: Mean RGB value (0..1) the released model subtracts from its inputs.
RGB_MEAN = (0.40066648, 0.39482617, 0.3784785)


class FlowNetCRobust(RefinementDecoder):
    """FlowNetCRobust on normalised frames whose size is a multiple of 64.

    Args:
        kernel_size: kernel of the encoder's convolutions after the first one (3 released).
        repeats: extra convolutions after each strided one in the encoder (3 released).

    Shape: ``image1``, ``image2`` ``(B, 3, H, W)`` -> ``(B, 2, H/4, W/4)`` flow in pixels of
    the input resolution.
    """

    def __init__(self, kernel_size: int = 3, repeats: int = 3):
        super().__init__()

        def stage(cin: int, cout: int, first_kernel: int) -> nn.ModuleList:
            return nn.ModuleList([conv_block(cin, cout, first_kernel, stride=2)]
                                 + [conv_block(cout, cout, kernel_size) for _ in range(repeats)])

        self.convs1 = stage(3, 64, 7)
        self.convs2 = stage(64, 128, kernel_size)
        self.convs3 = stage(128, 256, kernel_size)
        self.conv_redir = conv_block(256, 32, kernel_size=1)
        self.conv3_1 = conv_block(32 + 441, 256)
        self.conv4 = conv_block(256, 512, stride=2)
        self.conv4_1 = conv_block(512, 512)
        self.conv5 = conv_block(512, 512, stride=2)
        self.conv5_1 = conv_block(512, 512)
        self.conv6 = conv_block(512, 1024, stride=2)
        self.conv6_1 = conv_block(1024, 1024)
        self._add_decoder(deconv_bias=False, upsampler_bias=False)
        init_flownet_weights(self)

    @staticmethod
    def _run(layers: nn.ModuleList, x: torch.Tensor) -> torch.Tensor:
        for layer in layers:
            x = layer(x)
        return x

    def forward(self, image1: torch.Tensor, image2: torch.Tensor,
                gradient_checkpointing: bool = False) -> torch.Tensor:
        """``gradient_checkpointing``: recompute the encoder and the rest separately in the
        backward pass (less memory, about one more forward pass of time)."""
        b = image1.shape[0]
        both = torch.cat([image1, image2], dim=0)
        if gradient_checkpointing and torch.is_grad_enabled():
            conv2, conv3 = recompute(self._encode, both, use_reentrant=False)
            return recompute(self._match_and_decode, conv2[:b], conv3, use_reentrant=False)
        conv2, conv3 = self._encode(both)
        return self._match_and_decode(conv2[:b], conv3)

    def _encode(self, both: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Both frames (stacked on the batch) through the shared encoder: 1/4 and 1/8."""
        conv2 = self._run(self.convs2, self._run(self.convs1, both))
        conv3 = self._run(self.convs3, conv2)
        return conv2, conv3

    def _match_and_decode(self, conv2a: torch.Tensor, conv3: torch.Tensor) -> torch.Tensor:
        b = conv2a.shape[0]
        conv3a, conv3b = conv3[:b], conv3[b:]
        corr = F.leaky_relu(correlation(conv3a, conv3b, max_displacement=20, stride=2),
                            LEAKY_SLOPE)
        conv3_1 = self.conv3_1(torch.cat([self.conv_redir(conv3a), corr], dim=1))
        conv4 = self.conv4_1(self.conv4(conv3_1))
        conv5 = self.conv5_1(self.conv5(conv4))
        conv6 = self.conv6_1(self.conv6(conv5))
        return self.decode(conv6, conv5, conv4, conv3_1, conv2a)


class FlowNetCRobustModel(FlowModel):
    """FlowNetCRobust behind the package contract.

    Normalisation: RGB in ``[0, 1]`` minus the fixed mean :data:`RGB_MEAN` (the authors'
    ``normalize``). Padding: to a multiple of 64. Output: the 1/4-resolution prediction,
    upsampled bilinearly. ``iters`` is ignored (not recurrent); ``gradient_checkpointing``
    recomputes the encoder and the rest separately in the backward pass.
    """

    architecture = "flownetcrobust"
    multiple = 64

    def __init__(self, iters: Optional[int] = None, gradient_checkpointing: bool = False):
        super().__init__()
        self.network = FlowNetCRobust()
        self.gradient_checkpointing = gradient_checkpointing
        self.register_buffer("rgb_mean", torch.tensor(RGB_MEAN).view(1, 3, 1, 1),
                             persistent=False)

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        return image - self.rgb_mean.to(image.dtype)

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        flow = self.network(image1, image2, gradient_checkpointing=self.gradient_checkpointing)
        return upsample_bilinear(flow, 4)

    def load_checkpoint(self, state_dict: dict, source, what: str) -> None:
        """Load the released state dict, with or without ``module.``."""
        load_strict(self.network, strip_prefix(state_dict, "module."), source, what)


register_model(ModelSpec(
    name="flownetcrobust", build=FlowNetCRobustModel, default_checkpoint="flownetcrobust",
    description="FlowNetCRobust (Schrodi et al., CVPR 2022)"))
register_checkpoint(CheckpointSpec(
    "flownetcrobust", "flownetcrobust",
    "FlowNetCRobust as released by Schrodi et al. (CVPR 2022)",
    url="https://lmb.informatik.uni-freiburg.de/resources/binaries/cvpr22_adv_flow/"
        "RobustFlowNetC.pth"))
