"""FlowNet2 (Ilg et al., "FlowNet 2.0: Evolution of Optical Flow Estimation with Deep Networks",
CVPR 2017).

A stack of FlowNets for large displacements and a separate one for small ones, fused:

1. **FlowNetC** (:mod:`weathergen.models.flownetc`) on the two frames.
2. **FlowNetS x 2**: each sees both frames, frame 2 warped towards frame 1 with the previous
   estimate, that estimate (/20) and the brightness error of the warp (12 channels), and
   predicts an improved flow (the "CSS" stack).
3. **FlowNetSD**: a FlowNetS variant for small displacements (a stride-1 first layer, 3x3
   kernels, extra ``inter_conv`` layers in the decoder) on the two frames.
4. **Fusion network**: from frame 1, both flows, their magnitudes and the brightness errors of
   their warps (11 channels) it predicts the final flow at full resolution, in pixels.

Warping is bilinear with the border clamped (:func:`~weathergen.models.flownet_parts.warp`,
the original ``Resample2d``), magnitudes are Euclidean norms over channels
(:func:`~weathergen.models.flownet_parts.channel_norm`, the original ``ChannelNorm``).
Intermediate flows are upsampled by 4, bilinearly after FlowNetC and the first FlowNetS,
nearest-neighbour after the second FlowNetS and FlowNetSD; FlowNetSD's output is *divided* by
20 where the others are multiplied, as in the released code whose weights were converted
with it.

Module and parameter names follow ``FlowNet2_checkpoint.pth.tar`` of NVIDIA's flownet2-pytorch
release (``flownetc.*``, ``flownets_1.*``, ``flownets_2.*``, ``flownets_d.*``,
``flownetfusion.*``), so it loads as it is.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from .checkpoints import CheckpointSpec
from .flownet_parts import (FlowNetFamilyModel, RefinementDecoder, channel_norm, conv_block,
                            deconv_block, flow_upsampler, init_flownet_weights, inner_conv,
                            predict_flow, upsample_bilinear, upsample_nearest, warp)
from .flownetc import FLOW_DIVISOR, FlowNetC
from .registry import ModelSpec, register_checkpoint, register_model


class FlowNetS(RefinementDecoder):
    """FlowNetS with ``in_channels`` input channels (12 in FlowNet2).

    Shape: ``(B, in_channels, H, W)``, ``H``, ``W`` multiples of 64 -> ``(B, 2, H/4, W/4)``
    flow in 1/20 pixels.
    """

    def __init__(self, in_channels: int = 12):
        super().__init__()
        self.conv1 = conv_block(in_channels, 64, kernel_size=7, stride=2)
        self.conv2 = conv_block(64, 128, kernel_size=5, stride=2)
        self.conv3 = conv_block(128, 256, kernel_size=5, stride=2)
        self._add_deep_encoder(256)
        self._add_decoder(deconv_bias=True, upsampler_bias=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        conv2 = self.conv2(self.conv1(x))
        return self.decode(*self.encode_deep(self.conv3(conv2)), conv2)


class FlowNetSD(RefinementDecoder):
    """FlowNetSD: FlowNetS for small displacements (a stride-1 first layer, 3x3 kernels, an
    ``inter_conv`` before each flow prediction of the decoder).

    Shape: ``(B, 6, H, W)`` (both frames) -> ``(B, 2, H/4, W/4)``.
    """

    def __init__(self):
        super().__init__()
        self.conv0 = conv_block(6, 64)
        self.conv1 = conv_block(64, 64, stride=2)
        self.conv1_1 = conv_block(64, 128)
        self.conv2 = conv_block(128, 128, stride=2)
        self.conv2_1 = conv_block(128, 128)
        self.conv3 = conv_block(128, 256, stride=2)
        self._add_deep_encoder(256)
        self._add_decoder(deconv_bias=True, upsampler_bias=True, inter_conv=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        conv2 = self.conv2_1(self.conv2(self.conv1_1(self.conv1(self.conv0(x)))))
        return self.decode(*self.encode_deep(self.conv3(conv2)), conv2)


class FlowNetFusion(nn.Module):
    """The fusion network: full-resolution flow from the two stacks' flows and their errors.

    Shape: ``(B, 11, H, W)`` -> ``(B, 2, H, W)`` flow in pixels.
    """

    def __init__(self):
        super().__init__()
        self.conv0 = conv_block(11, 64)
        self.conv1 = conv_block(64, 64, stride=2)
        self.conv1_1 = conv_block(64, 128)
        self.conv2 = conv_block(128, 128, stride=2)
        self.conv2_1 = conv_block(128, 128)
        self.deconv1 = deconv_block(128, 32)
        self.deconv0 = deconv_block(128 + 32 + 2, 16)
        self.inter_conv1 = inner_conv(128 + 32 + 2, 32)
        self.inter_conv0 = inner_conv(64 + 16 + 2, 16)
        self.predict_flow2 = predict_flow(128)
        self.predict_flow1 = predict_flow(32)
        self.predict_flow0 = predict_flow(16)
        self.upsampled_flow2_to_1 = flow_upsampler(bias=True)
        self.upsampled_flow1_to_0 = flow_upsampler(bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        conv0 = self.conv0(x)
        conv1 = self.conv1_1(self.conv1(conv0))
        conv2 = self.conv2_1(self.conv2(conv1))
        flow2 = self.predict_flow2(conv2)
        concat1 = torch.cat([conv1, self.deconv1(conv2), self.upsampled_flow2_to_1(flow2)], 1)
        flow1 = self.predict_flow1(self.inter_conv1(concat1))
        concat0 = torch.cat([conv0, self.deconv0(concat1), self.upsampled_flow1_to_0(flow1)], 1)
        return self.predict_flow0(self.inter_conv0(concat0))


class FlowNet2(nn.Module):
    """FlowNet2 on mean-subtracted frames whose size is a multiple of 64.

    Shape: ``image1``, ``image2`` ``(B, 3, H, W)`` -> ``(B, 2, H, W)`` flow in pixels.
    """

    def __init__(self):
        super().__init__()
        self.flownetc = FlowNetC()
        self.flownets_1 = FlowNetS(12)
        self.flownets_2 = FlowNetS(12)
        self.flownets_d = FlowNetSD()
        self.flownetfusion = FlowNetFusion()
        init_flownet_weights(self)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor,
                gradient_checkpointing: bool = False) -> torch.Tensor:
        """``gradient_checkpointing``: recompute each sub-network in the backward pass instead
        of keeping its activations."""
        use_recompute = gradient_checkpointing and torch.is_grad_enabled()

        def run(net: nn.Module, *args: torch.Tensor) -> torch.Tensor:
            if use_recompute:
                return recompute(net, *args, use_reentrant=False)
            return net(*args)

        both = torch.cat([image1, image2], dim=1)
        div = FLOW_DIVISOR

        # FlowNetC, then two FlowNetS, each correcting the previous estimate.
        flow = upsample_bilinear(run(self.flownetc, image1, image2) * div, 4)
        for net, upsample in ((self.flownets_1, upsample_bilinear),
                              (self.flownets_2, upsample_nearest)):
            warped = warp(image2, flow)
            error = channel_norm(image1 - warped)
            flow = upsample(run(net, torch.cat([both, warped, flow / div, error], 1)) * div, 4)
        flow_css = flow

        # FlowNetSD (its output divided by 20, as in the release the weights come from).
        flow_sd = upsample_nearest(run(self.flownets_d, both) / div, 4)

        error_sd = channel_norm(image1 - warp(image2, flow_sd))
        error_css = channel_norm(image1 - warp(image2, flow_css))
        fusion_input = torch.cat([image1, flow_sd, flow_css, channel_norm(flow_sd),
                                  channel_norm(flow_css), error_sd, error_css], dim=1)
        return run(self.flownetfusion, fusion_input)


class FlowNet2Model(FlowNetFamilyModel):
    """FlowNet2 behind the package contract.

    Normalisation: RGB (the released PyTorch weights take RGB), minus the per-channel mean of
    the two (padded) frames, in units of 255 (``(x - mean) / rgb_max`` with ``rgb_max = 255``
    on 0..255 images). Padding: to a multiple of 64. ``iters`` is ignored (not recurrent);
    ``gradient_checkpointing`` recomputes each sub-network in the backward pass.
    """

    architecture = "flownet2"
    network_class = FlowNet2


register_model(ModelSpec(
    name="flownet2", build=FlowNet2Model, default_checkpoint="flownet2",
    description="FlowNet2 (Ilg et al., CVPR 2017), 162.5M parameters"))
register_checkpoint(CheckpointSpec(
    "flownet2", "flownet2",
    "FlowNet2 trained on FlyingChairs, then FlyingThings3D (Ilg et al.)",
    member="FlowNet2_checkpoint.pth.tar",
    page="https://drive.google.com/file/d/1LLYdnObBYzs7rDYYUCGscuC2nwO7y85I/view"))
