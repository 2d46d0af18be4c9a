"""Parts shared by the FlowNet family (FlowNetC, FlowNetCRobust, FlowNet2 and its sub-networks).

The FlowNet networks (Dosovitskiy et al., ICCV 2015; Ilg et al., CVPR 2017) are encoder-decoder
CNNs. Their released PyTorch checkpoints name layers after small building blocks, which this
module provides with the same parameter layout:

- :func:`conv_block`: a convolution with bias and a leaky ReLU (slope 0.1), stored as
  ``<name>.0.weight`` / ``<name>.0.bias`` (a two-element ``nn.Sequential``);
- :func:`deconv_block`: a 4x4 stride-2 transposed convolution and a leaky ReLU;
- :func:`predict_flow`: a 3x3 convolution to two channels (``<name>.weight``, ``<name>.bias``);
- :func:`flow_upsampler`: a learned 4x4 stride-2 transposed convolution of a flow field.

and the three operations the networks need besides convolutions, written with tensor operations
(the original code used compiled CUDA extensions for them):

- :func:`correlation`: FlowNetC's correlation layer, as matrix products in chunks (a block of
  columns and a few rows of displacements at a time) so that its memory stays bounded;
- :func:`warp`: backward warping with bilinear interpolation, clamped at the border
  (FlowNet2's ``Resample2d``);
- :func:`channel_norm`: the Euclidean norm over channels (FlowNet2's ``ChannelNorm``).

None of them works in place, so gradients reach the input images.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from .base import FlowModel, in_float32
from .checkpoints import load_strict, strip_prefix

#: Slope of the leaky ReLUs of every FlowNet.
LEAKY_SLOPE = 0.1

#: Bound on the elements of the frame-2 windows the correlation copies at a time
#: (2^24 floats: 64 MiB in float32).
CORRELATION_CHUNK_ELEMENTS = 1 << 24


class LeakyReLU(nn.Module):
    """Leaky ReLU with slope 0.1, never in place (the released code used ``inplace=True``)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.leaky_relu(x, LEAKY_SLOPE)


def conv_block(in_channels: int, out_channels: int, kernel_size: int = 3,
               stride: int = 1) -> nn.Sequential:
    """Convolution ("same" padding for odd kernels) with bias, then a leaky ReLU.

    Shape: ``(B, in_channels, H, W)`` -> ``(B, out_channels, H/stride, W/stride)``.
    """
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, kernel_size, stride=stride,
                                   padding=(kernel_size - 1) // 2, bias=True), LeakyReLU())


def inner_conv(in_channels: int, out_channels: int) -> nn.Sequential:
    """3x3 convolution with bias and no activation (FlowNetSD's and the fusion network's
    ``inter_conv`` layers, stored as ``<name>.0.*``)."""
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=True))


def deconv_block(in_channels: int, out_channels: int, bias: bool = True) -> nn.Sequential:
    """4x4 transposed convolution with stride 2 (doubles the size), then a leaky ReLU.

    Shape: ``(B, in_channels, H, W)`` -> ``(B, out_channels, 2H, 2W)``.
    """
    return nn.Sequential(nn.ConvTranspose2d(in_channels, out_channels, 4, stride=2, padding=1,
                                            bias=bias), LeakyReLU())


def predict_flow(in_channels: int) -> nn.Conv2d:
    """3x3 convolution to a two-channel flow estimate."""
    return nn.Conv2d(in_channels, 2, 3, padding=1, bias=True)


def flow_upsampler(bias: bool) -> nn.ConvTranspose2d:
    """Learned 2x upsampling of a flow estimate: ``(B, 2, H, W)`` -> ``(B, 2, 2H, 2W)``."""
    return nn.ConvTranspose2d(2, 2, 4, stride=2, padding=1, bias=bias)


def init_flownet_weights(module: nn.Module) -> None:
    """Initialise untrained weights (Xavier-uniform kernels, small biases).

    Only matters for untrained models (tests, benchmarks); released checkpoints overwrite it.
    """
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.uniform_(m.bias, -0.01, 0.01)


# ---------------------------------------------------------------------------------------------
# The encoder's deep stages and the refinement decoder shared by FlowNetS, FlowNetSD, FlowNetC
# and FlowNetCRobust
# ---------------------------------------------------------------------------------------------

class RefinementDecoder(nn.Module):
    """Base of the FlowNets whose encoder ends in the same deep stages (``conv3_1`` at 1/8 to
    ``conv6_1`` at 1/64) and whose decoder goes from 1/64 to 1/4 resolution in four steps.

    At each decoder step a transposed convolution doubles the decoder's features, a learned
    upsampler doubles the current flow estimate, and both are concatenated with the encoder's
    features of that resolution; the next flow estimate is predicted from that concatenation
    (FlowNetSD first passes it through an ``inter_conv`` layer). The layers are registered on the
    network itself (``conv4``, ``deconv5``, ``predict_flow6``, ...), in the order of the released
    files.

    Subclasses call :meth:`_add_deep_encoder` after their first stages, then
    :meth:`_add_decoder`; ``forward`` uses :meth:`encode_deep` and :meth:`decode`.
    """

    def _add_deep_encoder(self, conv3_1_in: int) -> None:
        """Register ``conv3_1`` (``conv3_1_in`` -> 256 channels at 1/8) to ``conv6_1``."""
        self.conv3_1 = conv_block(conv3_1_in, 256)
        self.conv4 = conv_block(256, 512, stride=2)
        self.conv4_1 = conv_block(512, 512)
        self.conv5 = conv_block(512, 512, stride=2)
        self.conv5_1 = conv_block(512, 512)
        self.conv6 = conv_block(512, 1024, stride=2)
        self.conv6_1 = conv_block(1024, 1024)

    def encode_deep(self, conv3_in: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(conv6, conv5, conv4, conv3)``: the deep stages from ``conv3_1``'s input at 1/8."""
        conv3 = self.conv3_1(conv3_in)
        conv4 = self.conv4_1(self.conv4(conv3))
        conv5 = self.conv5_1(self.conv5(conv4))
        conv6 = self.conv6_1(self.conv6(conv5))
        return conv6, conv5, conv4, conv3

    def _add_decoder(self, deconv_bias: bool, upsampler_bias: bool,
                     inter_conv: bool = False) -> None:
        """Register the decoder; ``inter_conv``: FlowNetSD's variant, a 3x3 convolution before
        each flow prediction (which then sees its output)."""
        self.deconv5 = deconv_block(1024, 512, bias=deconv_bias)
        self.deconv4 = deconv_block(1024 + 2, 256, bias=deconv_bias)
        self.deconv3 = deconv_block(512 + 256 + 2, 128, bias=deconv_bias)
        self.deconv2 = deconv_block(256 + 128 + 2, 64, bias=deconv_bias)
        concat = {5: 1024 + 2, 4: 512 + 256 + 2, 3: 256 + 128 + 2, 2: 128 + 64 + 2}
        if inter_conv:
            inner = {5: 512, 4: 256, 3: 128, 2: 64}
            for level in (5, 4, 3, 2):
                setattr(self, f"inter_conv{level}", inner_conv(concat[level], inner[level]))
            concat = inner
        self.predict_flow6 = predict_flow(1024)
        for level in (5, 4, 3, 2):
            setattr(self, f"predict_flow{level}", predict_flow(concat[level]))
        self.upsampled_flow6_to_5 = flow_upsampler(upsampler_bias)
        self.upsampled_flow5_to_4 = flow_upsampler(upsampler_bias)
        self.upsampled_flow4_to_3 = flow_upsampler(upsampler_bias)
        self.upsampled_flow3_to_2 = flow_upsampler(upsampler_bias)
        self._inter_conv = inter_conv

    def _predict(self, level: int, concat: torch.Tensor) -> torch.Tensor:
        if self._inter_conv:
            concat = getattr(self, f"inter_conv{level}")(concat)
        return getattr(self, f"predict_flow{level}")(concat)

    def decode(self, conv6: torch.Tensor, conv5: torch.Tensor, conv4: torch.Tensor,
               conv3: torch.Tensor, conv2: torch.Tensor) -> torch.Tensor:
        """Flow at 1/4 resolution from the encoder's features at 1/64 ... 1/4.

        Shape: ``conv6`` ``(B, 1024, H/64, W/64)``, ``conv5`` ``(B, 512, H/32, W/32)``,
        ``conv4`` ``(B, 512, H/16, W/16)``, ``conv3`` ``(B, 256, H/8, W/8)``, ``conv2``
        ``(B, 128, H/4, W/4)`` -> ``(B, 2, H/4, W/4)`` in the network's flow units.
        """
        flow6 = self.predict_flow6(conv6)
        concat5 = torch.cat([conv5, self.deconv5(conv6), self.upsampled_flow6_to_5(flow6)], 1)
        flow5 = self._predict(5, concat5)
        concat4 = torch.cat([conv4, self.deconv4(concat5), self.upsampled_flow5_to_4(flow5)], 1)
        flow4 = self._predict(4, concat4)
        concat3 = torch.cat([conv3, self.deconv3(concat4), self.upsampled_flow4_to_3(flow4)], 1)
        flow3 = self._predict(3, concat3)
        concat2 = torch.cat([conv2, self.deconv2(concat3), self.upsampled_flow3_to_2(flow3)], 1)
        return self._predict(2, concat2)


class CorrelationFlowNet(RefinementDecoder):
    """Base of FlowNetC and FlowNetCRobust: a shared encoder on both frames to 1/8, the
    correlation of the two frames' 1/8 features (displacements up to 20 pixels at stride 2:
    441 channels) beside frame 1's redirected features, then the deep stages and the decoder.

    Subclasses register their encoder, then call :meth:`_add_correlation_head`, then
    :meth:`_add_decoder`, and implement :meth:`_encode`.

    Shape: ``image1``, ``image2`` ``(B, 3, H, W)`` (multiples of 64) -> ``(B, 2, H/4, W/4)``.
    """

    def _add_correlation_head(self) -> None:
        self.conv_redir = conv_block(256, 32, kernel_size=1)
        self._add_deep_encoder(32 + 441)

    def _encode(self, both: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Both frames (stacked on the batch) through the shared encoder: 1/4 and 1/8."""
        raise NotImplementedError

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

    def _match_and_decode(self, conv2a: torch.Tensor, conv3: torch.Tensor) -> torch.Tensor:
        b = conv2a.shape[0]
        conv3a, conv3b = conv3[:b], conv3[b:]
        corr = F.leaky_relu(correlation(conv3a, conv3b, max_displacement=20, stride=2),
                            LEAKY_SLOPE)
        conv6, conv5, conv4, conv3_1 = self.encode_deep(
            torch.cat([self.conv_redir(conv3a), corr], dim=1))
        return self.decode(conv6, conv5, conv4, conv3_1, conv2a)


class FlowNetFamilyModel(FlowModel):
    """What the FlowNet adapters share: a network of the family (:attr:`network_class`) as
    ``network``, padding to a multiple of 64, ``gradient_checkpointing`` handed to the network,
    and the released files loaded strictly with or without the ``module.`` prefix. ``iters`` is
    accepted for a uniform interface and ignored (the FlowNets are not recurrent).

    By default (FlowNetC, FlowNet2) the frames are RGB (the released PyTorch weights take RGB)
    minus the per-channel mean of the two (padded) frames (:func:`subtract_joint_mean`)."""

    multiple = 64
    #: The network, built without arguments.
    network_class: type = nn.Module

    def __init__(self, iters: Optional[int] = None, gradient_checkpointing: bool = False):
        super().__init__()
        self.network = self.network_class()
        self.gradient_checkpointing = gradient_checkpointing

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        return image  # the mean of both frames is subtracted in predict

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        x1, x2 = subtract_joint_mean(image1, image2)
        return self.network(x1, x2, gradient_checkpointing=self.gradient_checkpointing)

    def load_checkpoint(self, state_dict: dict, source, what: str) -> None:
        """Load the released file (its ``state_dict``), with or without ``module.``."""
        load_strict(self.network, strip_prefix(state_dict, "module."), source, what)


def subtract_joint_mean(image1: torch.Tensor,
                        image2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Subtract from both frames the per-channel mean over both frames (FlowNet2's input
    normalisation: ``(x - mean) / 255`` on 0..255 images is ``x - mean`` on 0..1 images)."""
    mean = torch.stack([image1, image2], dim=2).mean(dim=(2, 3, 4), keepdim=True).squeeze(2)
    return image1 - mean, image2 - mean


# ---------------------------------------------------------------------------------------------
# Correlation, warping, channel norm
# ---------------------------------------------------------------------------------------------

@in_float32
def correlation(features1: torch.Tensor, features2: torch.Tensor, max_displacement: int = 20,
                stride: int = 2, block: int = 32,
                chunk_elements: int = CORRELATION_CHUNK_ELEMENTS) -> torch.Tensor:
    """FlowNetC's correlation: mean over channels of ``f1(x) * f2(x + d)`` for a grid of ``d``.

    The displacements ``d = (dx, dy)`` run over ``-max_displacement ... max_displacement`` in
    steps of ``stride`` in each direction (21 x 21 = 441 for FlowNetC); output channel
    ``i * n + j`` holds ``dy = i * stride - max_displacement`` and
    ``dx = j * stride - max_displacement`` (``dy`` varies slowest), as in the released models.
    Features of frame 2 outside the map count as zero.

    Computed with matrix products, in chunks: for each block of ``block`` columns and a few
    displacement rows ``dy`` at a time, the products of every feature vector of frame 1 in the
    block with every one of frame 2 within reach (``block + 2 * max_displacement`` columns,
    row ``y + dy``) form small matrices, from which the ``n`` wanted diagonals are read. A
    chunk copies at most about ``chunk_elements`` elements of frame 2's features, so the
    working memory of the forward pass is bounded at any image size; the backward pass keeps
    these copies (in all about ``n * (block + 2 * max_displacement) / block`` times the
    features of frame 2, plus copies of frame 1's: about half a GiB for a Sintel frame at
    FlowNetC's 1/8 resolution).

    Shape: ``features1``, ``features2`` ``(B, C, H, W)`` -> ``(B, n*n, H, W)`` with
    ``n = 2 * (max_displacement // stride) + 1``.
    """
    if features1.shape != features2.shape:
        raise ValueError(f"expected feature maps of one shape, got {tuple(features1.shape)} "
                         f"and {tuple(features2.shape)}")
    if max_displacement % stride:
        raise ValueError(f"max_displacement {max_displacement} is not a multiple of the "
                         f"stride {stride}")
    b, c, h, w = features1.shape
    d = max_displacement
    n = 2 * (d // stride) + 1
    f1 = features1.permute(0, 2, 3, 1).unsqueeze(1)  # (B, 1, H, W, C)
    # (B, H + 2d, C, W + 2d): frame 2 with zeros around, rows first
    padded = F.pad(features2, (d, d, d, d)).permute(0, 2, 1, 3)
    blocks = []
    for x0 in range(0, w, block):
        bw = min(block, w - x0)
        reach = bw + 2 * d
        # (B, n_dy, H, C, reach): for displacement row i, the padded rows y + i * stride and the
        # columns a block's displacements reach (a strided view, copied chunk by chunk below).
        windows = padded[..., x0:x0 + reach].unfold(1, h, stride).permute(0, 1, 4, 2, 3)
        per_row = b * h * c * reach
        rows = max(1, min(n, chunk_elements // per_row))
        chunks = []
        for i in range(0, n, rows):
            # products (B, k, H, bw, reach): frame-1 column x0 + x with padded column x0 + x'
            products = torch.matmul(f1[:, :, :, x0:x0 + bw], windows[:, i:i + rows])
            k = products.shape[1]
            # Displacement j of column x sits at x' = x + j * stride, i.e. at flat index
            # x * (reach + 1) + j * stride: pad the flattened rows by bw, fold them into rows
            # of reach + 1, and every wanted value is in the first n * stride columns.
            flat = F.pad(products.reshape(b, k, h, bw * reach), (0, bw))
            chunks.append(flat.reshape(b, k, h, bw, reach + 1)[..., 0:(n - 1) * stride + 1:stride])
        blocks.append(torch.cat(chunks, dim=1))  # (B, n_dy, H, bw, n_dx)
    out = torch.cat(blocks, dim=3)  # (B, n_dy, H, W, n_dx)
    return out.permute(0, 1, 4, 2, 3).reshape(b, n * n, h, w) / c


@in_float32
def warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Sample ``image`` at ``x + flow(x)`` with bilinear interpolation, clamped at the border.

    Positions outside the image take the nearest border value, as FlowNet2's ``Resample2d``
    (which clamps each of the four interpolation corners into the image).

    Shape: ``image`` ``(B, C, H, W)``, ``flow`` ``(B, 2, H, W)`` in pixels -> ``(B, C, H, W)``.
    """
    b, _, h, w = flow.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=flow.dtype, device=flow.device),
                            torch.arange(w, dtype=flow.dtype, device=flow.device),
                            indexing="ij")
    x = xs + flow[:, 0]
    y = ys + flow[:, 1]
    # align_corners=True: -1 and 1 are the centres of the border pixels.
    grid = torch.stack([2.0 * x / max(w - 1, 1) - 1.0, 2.0 * y / max(h - 1, 1) - 1.0], dim=-1)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="border",
                         align_corners=True)


def channel_norm(x: torch.Tensor) -> torch.Tensor:
    """Euclidean norm over the channels; its gradient is zero (not NaN) where the norm is zero.

    Shape: ``(B, C, H, W)`` -> ``(B, 1, H, W)``.
    """
    return torch.linalg.vector_norm(x, ord=2, dim=1, keepdim=True)


def upsample_bilinear(flow: torch.Tensor, factor: int = 4) -> torch.Tensor:
    """Bilinear upsampling by ``factor`` (half-pixel centres, PyTorch's default for the
    ``nn.Upsample(scale_factor=4, mode='bilinear')`` of the released code). Values unchanged."""
    return F.interpolate(flow, scale_factor=factor, mode="bilinear", align_corners=False)


def upsample_nearest(flow: torch.Tensor, factor: int = 4) -> torch.Tensor:
    """Nearest-neighbour upsampling by ``factor``. Values unchanged."""
    return F.interpolate(flow, scale_factor=factor, mode="nearest")
