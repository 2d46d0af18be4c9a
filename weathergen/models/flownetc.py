"""FlowNetC (Dosovitskiy et al., ICCV 2015), as released with FlowNet2 (Ilg et al., CVPR 2017).

The network:

1. **Siamese encoder**: the same three strided convolutions (7x7, 5x5, 5x5; 64, 128, 256
   channels) turn each frame into features at 1/8 resolution.
2. **Correlation**: the features of frame 1 are compared with those of frame 2 at 21 x 21
   displacements (up to 20 feature pixels in steps of 2), giving 441 channels; a 1x1
   convolution of frame 1's features (``conv_redir``, 32 channels) is concatenated.
3. **Encoder, second part**: strided convolutions down to 1/64 resolution.
4. **Refinement decoder** (:class:`~weathergen.models.flownet_parts.RefinementDecoder`): back
   up to 1/4 resolution, predicting a flow at every scale from the previous one.

The flow is predicted at 1/4 resolution in units of 1/20 pixel (the training targets were
divided by 20); the adapter multiplies by 20 and upsamples bilinearly by 4.

Module and parameter names follow the checkpoint ``FlowNet2-C_checkpoint.pth.tar`` of NVIDIA's
flownet2-pytorch release (the Caffe model of the FlowNet2 authors, converted), so it loads as
it is. FlowNet2 (:mod:`weathergen.models.flownet2`) uses this network as its first stage.
"""

from __future__ import annotations

import torch

from .checkpoints import CheckpointSpec
from .flownet_parts import (CorrelationFlowNet, FlowNetFamilyModel, conv_block,
                            init_flownet_weights, subtract_joint_mean, upsample_bilinear)
from .registry import ModelSpec, register_checkpoint, register_model

#: The FlowNet2 family predicts flow divided by this factor at its internal resolutions.
FLOW_DIVISOR = 20.0


class FlowNetC(CorrelationFlowNet):
    """FlowNetC on normalised frames whose size is a multiple of 64.

    Shape: ``image1``, ``image2`` ``(B, 3, H, W)`` -> ``(B, 2, H/4, W/4)`` flow in 1/20 pixels
    of the input resolution.
    """

    def __init__(self):
        super().__init__()
        self.conv1 = conv_block(3, 64, kernel_size=7, stride=2)
        self.conv2 = conv_block(64, 128, kernel_size=5, stride=2)
        self.conv3 = conv_block(128, 256, kernel_size=5, stride=2)
        self._add_correlation_head()
        self._add_decoder(deconv_bias=True, upsampler_bias=True)
        init_flownet_weights(self)

    def _encode(self, both: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        conv2 = self.conv2(self.conv1(both))
        return conv2, self.conv3(conv2)


class FlowNetCModel(FlowNetFamilyModel):
    """FlowNetC behind the package contract: RGB in ``[0, 1]`` of any size in, flow in pixels out.

    Normalisation: RGB (the released PyTorch weights take RGB), minus the per-channel mean of
    the two (padded) frames. Padding: to a multiple of 64. Output: 20 x the 1/4-resolution
    prediction, upsampled bilinearly.

    ``iters`` is accepted for a uniform interface and ignored (FlowNetC is not recurrent);
    ``gradient_checkpointing`` recomputes the encoder and the rest separately in the
    backward pass.
    """

    architecture = "flownetc"
    network_class = FlowNetC

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        return upsample_bilinear(FLOW_DIVISOR * super().predict(image1, image2), 4)


#: Where NVIDIA's flownet2-pytorch publishes the converted FlowNet2 checkpoints (Google Drive
#: pages, no direct download address); the README of github.com/NVIDIA/flownet2-pytorch links
#: them.
FLOWNET2_C_PAGE = "https://drive.google.com/file/d/1elgK52N4EQVi5ywN2Ky4qWvweLh8RE2U/view"

register_model(ModelSpec(
    name="flownetc", build=FlowNetCModel, default_checkpoint="flownetc",
    description="FlowNetC (Dosovitskiy et al., ICCV 2015) as in FlowNet2, 39.2M parameters"))
register_checkpoint(CheckpointSpec(
    "flownetc", "flownetc",
    "FlowNet2-C: FlowNetC trained on FlyingChairs, then FlyingThings3D (Ilg et al.)",
    member="FlowNet2-C_checkpoint.pth.tar", page=FLOWNET2_C_PAGE))

__all__ = ["FlowNetC", "FlowNetCModel", "subtract_joint_mean", "FLOW_DIVISOR"]
