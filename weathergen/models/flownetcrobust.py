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
from torch import nn

from .checkpoints import CheckpointSpec
from .flownet_parts import (CorrelationFlowNet, FlowNetFamilyModel, conv_block,
                            init_flownet_weights, upsample_bilinear)
from .registry import ModelSpec, register_checkpoint, register_model

#: Mean RGB value (0..1) the released model subtracts from its inputs.
RGB_MEAN = (0.40066648, 0.39482617, 0.3784785)


class FlowNetCRobust(CorrelationFlowNet):
    """FlowNetCRobust on normalised frames whose size is a multiple of 64.

    Args:
        kernel_size: kernel of the encoder's convolutions after the first one (3 released).
        repeats: extra convolutions after each strided one in the encoder (3 released).

    Shape: ``image1``, ``image2`` ``(B, 3, H, W)`` -> ``(B, 2, H/4, W/4)`` flow in pixels of
    the input resolution.
    """

    def __init__(self, kernel_size: int = 3, repeats: int = 3):
        super().__init__()

        def stage(cin: int, cout: int, first_kernel: int) -> nn.Sequential:
            # an nn.Sequential names its layers 0, 1, ... as the released ModuleList does
            return nn.Sequential(conv_block(cin, cout, first_kernel, stride=2),
                                 *[conv_block(cout, cout, kernel_size) for _ in range(repeats)])

        self.convs1 = stage(3, 64, 7)
        self.convs2 = stage(64, 128, kernel_size)
        self.convs3 = stage(128, 256, kernel_size)
        self._add_correlation_head()
        self._add_decoder(deconv_bias=False, upsampler_bias=False)
        init_flownet_weights(self)

    def _encode(self, both: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        conv2 = self.convs2(self.convs1(both))
        return conv2, self.convs3(conv2)


class FlowNetCRobustModel(FlowNetFamilyModel):
    """FlowNetCRobust behind the package contract.

    Normalisation: RGB in ``[0, 1]`` minus the fixed mean :data:`RGB_MEAN` (the authors'
    ``normalize``). Padding: to a multiple of 64. Output: the 1/4-resolution prediction,
    upsampled bilinearly. ``iters`` is ignored (not recurrent); ``gradient_checkpointing``
    recomputes the encoder and the rest separately in the backward pass.
    """

    architecture = "flownetcrobust"
    network_class = FlowNetCRobust

    def __init__(self, iters: Optional[int] = None, gradient_checkpointing: bool = False):
        super().__init__(iters, gradient_checkpointing)
        self.register_buffer("rgb_mean", torch.tensor(RGB_MEAN).view(1, 3, 1, 1),
                             persistent=False)

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        return image - self.rgb_mean.to(image.dtype)

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        flow = self.network(image1, image2, gradient_checkpointing=self.gradient_checkpointing)
        return upsample_bilinear(flow, 4)


register_model(ModelSpec(
    name="flownetcrobust", build=FlowNetCRobustModel, default_checkpoint="flownetcrobust",
    description="FlowNetCRobust (Schrodi et al., CVPR 2022)"))
register_checkpoint(CheckpointSpec(
    "flownetcrobust", "flownetcrobust",
    "FlowNetCRobust as released by Schrodi et al. (CVPR 2022)",
    url="https://lmb.informatik.uni-freiburg.de/resources/binaries/cvpr22_adv_flow/"
        "RobustFlowNetC.pth"))
