"""RAFT and RAFT-small: Recurrent All-Pairs Field Transforms (Teed and Deng, ECCV 2020).

The network, in the paper's parts (one section each below):

1. **Feature and context encoders** (paper Sec. 3.1): two CNNs at 1/8 resolution. The feature
   encoder ``fnet`` sees both frames; the context encoder ``cnet`` sees frame 1 only and gives the
   initial hidden state of the update operator and a context input it reads at every step.
2. **Correlation pyramid and lookup** (Sec. 3.2): the dot product of every feature vector of
   frame 1 with every one of frame 2, pooled to 4 levels; at each step, values in a window of
   radius ``r`` around the current estimate of each pixel's position in frame 2 are sampled.
3. **Update operator** (Sec. 3.3): a motion encoder turns the sampled correlations and the current
   flow into features; a convolutional GRU (separable 1x5/5x1 for RAFT, 3x3 for RAFT-small)
   updates the hidden state; a flow head predicts a residual flow.
4. **Upsampling** (Sec. 3.3): RAFT predicts, per coarse pixel, a convex combination of its 3x3
   coarse neighbours for each of the 8x8 fine pixels; RAFT-small upsamples bilinearly.

Module and parameter names follow the key layout of the checkpoints the authors released, so those
files load as they are (see :meth:`RAFTModel.load_checkpoint`). Two details of that layout
constrain the code: residual blocks register their shortcut normalisation twice (as ``norm3`` and
as ``downsample.1``), and the correlation features are ordered with the x offset varying slowest.

Shapes below: ``B`` batch, ``H, W`` padded input size, ``h = H/8, w = W/8`` the working resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from .base import IteratedFlowModel, autocast_mode, mixed_precision
from .checkpoints import CheckpointSpec
from .registry import ModelSpec, register_checkpoint, register_model


@dataclass(frozen=True)
class RAFTConfig:
    """Sizes of one RAFT variant.

    Attributes:
        small: RAFT-small (bottleneck encoders, 3x3 GRU, bilinear upsampling) or full RAFT.
        hidden_dim: channels of the GRU's hidden state.
        context_dim: channels of the context features fed to the GRU at every step.
        feature_dim: channels of the features that are correlated.
        corr_levels: levels of the correlation pyramid.
        corr_radius: lookup radius in pixels of each level (a (2r+1)^2 window).
    """

    small: bool
    hidden_dim: int
    context_dim: int
    feature_dim: int
    corr_levels: int = 4
    corr_radius: int = 4

    @property
    def corr_channels(self) -> int:
        return self.corr_levels * (2 * self.corr_radius + 1) ** 2


RAFT_FULL = RAFTConfig(small=False, hidden_dim=128, context_dim=128, feature_dim=256,
                       corr_radius=4)
RAFT_SMALL = RAFTConfig(small=True, hidden_dim=96, context_dim=64, feature_dim=128,
                        corr_radius=3)

#: Refinement iterations when none are given (the authors' setting for Sintel evaluation).
DEFAULT_ITERS = 12


# ---------------------------------------------------------------------------------------------
# 1. Feature and context encoders
# ---------------------------------------------------------------------------------------------

def _norm(kind: str, channels: int) -> nn.Module:
    """The normalisation layers the released models use.

    ``instance`` (feature encoders) has no parameters; ``batch`` (RAFT's context encoder) has
    running statistics in the checkpoint; ``none`` (RAFT-small's context encoder) is identity.
    """
    if kind == "instance":
        return nn.InstanceNorm2d(channels)
    if kind == "batch":
        return nn.BatchNorm2d(channels)
    if kind == "group":
        return nn.GroupNorm(num_groups=channels // 8, num_channels=channels)
    if kind == "none":
        return nn.Identity()
    raise ValueError(f"unknown normalisation {kind!r}")


class ResidualBlock(nn.Module):
    """Two 3x3 convolutions with a shortcut (RAFT's encoders).

    Shape: ``(B, in_planes, H, W)`` -> ``(B, planes, H/stride, W/stride)``.
    """

    def __init__(self, in_planes: int, planes: int, norm: str, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_planes, planes, 3, padding=1, stride=stride)
        self.conv2 = nn.Conv2d(planes, planes, 3, padding=1)
        self.norm1 = _norm(norm, planes)
        self.norm2 = _norm(norm, planes)
        self.downsample = None
        if stride != 1:
            # The same module under two names: the released checkpoints hold its statistics as
            # both "norm3.*" and "downsample.1.*".
            self.norm3 = _norm(norm, planes)
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, planes, 1, stride=stride),
                                            self.norm3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = F.relu(self.norm2(self.conv2(y)))
        shortcut = x if self.downsample is None else self.downsample(x)
        return F.relu(shortcut + y)


class BottleneckBlock(nn.Module):
    """1x1 -> 3x3 -> 1x1 convolutions at a quarter of the width, with a shortcut (RAFT-small).

    Shape: ``(B, in_planes, H, W)`` -> ``(B, planes, H/stride, W/stride)``.
    """

    def __init__(self, in_planes: int, planes: int, norm: str, stride: int = 1):
        super().__init__()
        inner = planes // 4
        self.conv1 = nn.Conv2d(in_planes, inner, 1)
        self.conv2 = nn.Conv2d(inner, inner, 3, padding=1, stride=stride)
        self.conv3 = nn.Conv2d(inner, planes, 1)
        self.norm1 = _norm(norm, inner)
        self.norm2 = _norm(norm, inner)
        self.norm3 = _norm(norm, planes)
        self.downsample = None
        if stride != 1:
            self.norm4 = _norm(norm, planes)  # registered twice, as in ResidualBlock
            self.downsample = nn.Sequential(nn.Conv2d(in_planes, planes, 1, stride=stride),
                                            self.norm4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        y = F.relu(self.norm2(self.conv2(y)))
        y = F.relu(self.norm3(self.conv3(y)))
        shortcut = x if self.downsample is None else self.downsample(x)
        return F.relu(shortcut + y)


class Encoder(nn.Module):
    """A 7x7 stride-2 stem, three stages of two blocks (the 2nd and 3rd halve the size), a 1x1 head.

    Widths: 64 / 64, 96, 128 for RAFT (residual blocks), 32 / 32, 64, 96 for RAFT-small
    (bottleneck blocks).

    Shape: ``(B, 3, H, W)`` in ``[-1, 1]`` -> ``(B, output_dim, H/8, W/8)``.
    """

    def __init__(self, output_dim: int, norm: str, small: bool):
        super().__init__()
        stem, widths = (32, (32, 64, 96)) if small else (64, (64, 96, 128))
        block = BottleneckBlock if small else ResidualBlock
        self.conv1 = nn.Conv2d(3, stem, 7, stride=2, padding=3)
        self.norm1 = _norm(norm, stem)
        self.layer1 = nn.Sequential(block(stem, widths[0], norm, 1),
                                    block(widths[0], widths[0], norm))
        self.layer2 = nn.Sequential(block(widths[0], widths[1], norm, 2),
                                    block(widths[1], widths[1], norm))
        self.layer3 = nn.Sequential(block(widths[1], widths[2], norm, 2),
                                    block(widths[2], widths[2], norm))
        self.conv2 = nn.Conv2d(widths[2], output_dim, 1)
        for m in self.modules():
            # Only matters for untrained models (tests, training from scratch): keeps
            # activations at a sensible scale through the stack of ReLU blocks.
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.norm1(self.conv1(x)))
        x = self.layer3(self.layer2(self.layer1(x)))
        return self.conv2(x)


# ---------------------------------------------------------------------------------------------
# 2. Correlation pyramid and lookup
# ---------------------------------------------------------------------------------------------

def sample_bilinear(image: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``image`` at pixel positions ``points``; zero outside the image.

    Pixel positions use the package convention (the centre of the top-left pixel is ``(0, 0)``).

    Shape:
        image: ``(N, C, H, W)``; points: ``(N, P, Q, 2)`` as ``(x, y)`` -> ``(N, C, P, Q)``.
    """
    h, w = image.shape[-2:]
    # With align_corners=False, normalised -1 and 1 are the outer edges of the border pixels,
    # so centre x maps to (2x + 1)/w - 1; unlike the align_corners=True form this also holds
    # for levels only one pixel wide.
    scale = torch.tensor([2.0 / w, 2.0 / h], dtype=points.dtype, device=points.device)
    grid = (points + 0.5) * scale - 1.0
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


class CorrelationPyramid:
    """All-pairs correlation volume of two feature maps, pooled into a pyramid, with lookup.

    Level 0 holds ``<f1(i, j), f2(k, l)> / sqrt(D)`` for every pixel ``(i, j)`` of frame 1 and
    ``(k, l)`` of frame 2; level ``n`` averages 2^n x 2^n blocks over the frame-2 dimensions.

    Shape:
        fmap1, fmap2: ``(B, D, h, w)``.
        lookup: coords ``(B, 2, h, w)`` -> ``(B, L*(2r+1)^2, h, w)``.
    """

    def __init__(self, fmap1: torch.Tensor, fmap2: torch.Tensor, levels: int, radius: int):
        b, d, h, w = fmap1.shape
        corr = torch.matmul(fmap1.flatten(2).transpose(1, 2), fmap2.flatten(2)) / math.sqrt(d)
        corr = corr.reshape(b * h * w, 1, h, w)  # one frame-2 "image" per frame-1 pixel
        self.levels = [corr]
        for _ in range(levels - 1):
            corr = F.avg_pool2d(corr, 2, stride=2)
            self.levels.append(corr)
        self.radius = radius
        # Window offsets as (dx, dy); the trained weights expect dx to vary slowest.
        steps = torch.arange(-radius, radius + 1, dtype=fmap1.dtype, device=fmap1.device)
        dx = steps.repeat_interleave(2 * radius + 1)
        dy = steps.repeat(2 * radius + 1)
        self.offsets = torch.stack([dx, dy], dim=-1).view(1, -1, 1, 2)  # (1, (2r+1)^2, 1, 2)

    def lookup(self, coords: torch.Tensor) -> torch.Tensor:
        """Correlation values in a window around ``coords``: positions in frame 2, in level-0
        pixels."""
        b, _, h, w = coords.shape
        centres = coords.permute(0, 2, 3, 1).reshape(b * h * w, 1, 1, 2)
        out = []
        for n, corr in enumerate(self.levels):
            # Level n is indexed by position / 2^n (not (position + 0.5) / 2^n - 0.5): that is
            # how the released models were trained.
            points = centres / (2 ** n) + self.offsets
            values = sample_bilinear(corr, points)  # (b*h*w, 1, (2r+1)^2, 1)
            out.append(values.view(b, h, w, -1))
        return torch.cat(out, dim=-1).permute(0, 3, 1, 2).contiguous()


# ---------------------------------------------------------------------------------------------
# 3. Update operator: motion encoder, (Sep)ConvGRU, flow head
# ---------------------------------------------------------------------------------------------

class MotionEncoder(nn.Module):
    """Features of the sampled correlations and of the current flow, plus the flow itself.

    Shape: flow ``(B, 2, h, w)``, corr ``(B, corr_channels, h, w)`` -> ``(B, out_dim, h, w)``
    with ``out_dim`` 128 (RAFT) or 82 (RAFT-small); the last two channels are the flow.
    """

    def __init__(self, corr_channels: int, small: bool):
        super().__init__()
        if small:
            self.convc1 = nn.Conv2d(corr_channels, 96, 1)
            self.convc2 = None
            self.convf1 = nn.Conv2d(2, 64, 7, padding=3)
            self.convf2 = nn.Conv2d(64, 32, 3, padding=1)
            self.conv = nn.Conv2d(96 + 32, 80, 3, padding=1)
        else:
            self.convc1 = nn.Conv2d(corr_channels, 256, 1)
            self.convc2 = nn.Conv2d(256, 192, 3, padding=1)
            self.convf1 = nn.Conv2d(2, 128, 7, padding=3)
            self.convf2 = nn.Conv2d(128, 64, 3, padding=1)
            self.conv = nn.Conv2d(192 + 64, 128 - 2, 3, padding=1)
        self.out_dim = self.conv.out_channels + 2

    def forward(self, flow: torch.Tensor, corr: torch.Tensor) -> torch.Tensor:
        c = F.relu(self.convc1(corr))
        if self.convc2 is not None:
            c = F.relu(self.convc2(c))
        f = F.relu(self.convf2(F.relu(self.convf1(flow))))
        features = F.relu(self.conv(torch.cat([c, f], dim=1)))
        return torch.cat([features, flow], dim=1)


def _gru_update(h: torch.Tensor, x: torch.Tensor, convz: nn.Module, convr: nn.Module,
                convq: nn.Module) -> torch.Tensor:
    """One GRU step with convolutional gates: z, r from [h, x]; candidate q from [r*h, x]."""
    hx = torch.cat([h, x], dim=1)
    z = torch.sigmoid(convz(hx))
    r = torch.sigmoid(convr(hx))
    q = torch.tanh(convq(torch.cat([r * h, x], dim=1)))
    return (1 - z) * h + z * q


class ConvGRU(nn.Module):
    """GRU with 3x3 convolutional gates (RAFT-small).

    Shape: h ``(B, hidden_dim, h, w)``, x ``(B, input_dim, h, w)`` -> ``(B, hidden_dim, h, w)``.
    """

    def __init__(self, hidden_dim: int, input_dim: int):
        super().__init__()
        channels = hidden_dim + input_dim
        self.convz = nn.Conv2d(channels, hidden_dim, 3, padding=1)
        self.convr = nn.Conv2d(channels, hidden_dim, 3, padding=1)
        self.convq = nn.Conv2d(channels, hidden_dim, 3, padding=1)

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return _gru_update(h, x, self.convz, self.convr, self.convq)


class SepConvGRU(nn.Module):
    """Two GRU steps, with 1x5 then 5x1 gates: a 5x5 receptive field at lower cost (RAFT).

    Shape: as :class:`ConvGRU`.
    """

    def __init__(self, hidden_dim: int, input_dim: int):
        super().__init__()
        channels = hidden_dim + input_dim
        horizontal = dict(kernel_size=(1, 5), padding=(0, 2))
        vertical = dict(kernel_size=(5, 1), padding=(2, 0))
        self.convz1 = nn.Conv2d(channels, hidden_dim, **horizontal)
        self.convr1 = nn.Conv2d(channels, hidden_dim, **horizontal)
        self.convq1 = nn.Conv2d(channels, hidden_dim, **horizontal)
        self.convz2 = nn.Conv2d(channels, hidden_dim, **vertical)
        self.convr2 = nn.Conv2d(channels, hidden_dim, **vertical)
        self.convq2 = nn.Conv2d(channels, hidden_dim, **vertical)

    def forward(self, h: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        h = _gru_update(h, x, self.convz1, self.convr1, self.convq1)
        return _gru_update(h, x, self.convz2, self.convr2, self.convq2)


class FlowHead(nn.Module):
    """Residual flow from the hidden state. Shape: ``(B, C, h, w)`` -> ``(B, 2, h, w)``."""

    def __init__(self, input_dim: int, hidden_dim: int):
        super().__init__()
        self.conv1 = nn.Conv2d(input_dim, hidden_dim, 3, padding=1)
        self.conv2 = nn.Conv2d(hidden_dim, 2, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(F.relu(self.conv1(x)))


class UpdateBlock(nn.Module):
    """One refinement step: motion features -> GRU -> residual flow (and, for RAFT, the
    convex-upsampling weights, computed on demand by :meth:`upsampling_weights`)."""

    def __init__(self, config: RAFTConfig):
        super().__init__()
        self.encoder = MotionEncoder(config.corr_channels, config.small)
        gru = ConvGRU if config.small else SepConvGRU
        self.gru = gru(config.hidden_dim, config.context_dim + self.encoder.out_dim)
        self.flow_head = FlowHead(config.hidden_dim, 128 if config.small else 256)
        self.mask = None
        if not config.small:
            # 9 neighbour weights for each of the 8x8 fine pixels of a coarse pixel.
            self.mask = nn.Sequential(nn.Conv2d(config.hidden_dim, 256, 3, padding=1), nn.ReLU(),
                                      nn.Conv2d(256, 9 * 8 * 8, 1))

    def forward(self, hidden: torch.Tensor, context: torch.Tensor, corr: torch.Tensor,
                flow: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Shape: hidden ``(B, hidden_dim, h, w)``, context ``(B, context_dim, h, w)``, corr
        ``(B, corr_channels, h, w)``, flow ``(B, 2, h, w)`` -> (new hidden, residual flow
        ``(B, 2, h, w)``), flows in pixels of the working resolution."""
        x = torch.cat([context, self.encoder(flow, corr)], dim=1)
        hidden = self.gru(hidden, x)
        return hidden, self.flow_head(hidden)

    def upsampling_weights(self, hidden: torch.Tensor) -> torch.Tensor:
        """Logits of the convex-upsampling weights, ``(B, 576, h, w)`` (RAFT only)."""
        # The factor 0.25 is part of the trained model (it was used to balance gradients).
        return 0.25 * self.mask(hidden)


# ---------------------------------------------------------------------------------------------
# 4. Upsampling
# ---------------------------------------------------------------------------------------------

def convex_upsample(flow: torch.Tensor, logits: torch.Tensor, factor: int = 8) -> torch.Tensor:
    """Each fine pixel is a convex combination of the 3x3 coarse flow vectors around its cell.

    Shape: flow ``(B, 2, h, w)`` in coarse pixels, logits ``(B, 9*factor^2, h, w)`` ordered
    (neighbour, fine row, fine column) -> ``(B, 2, factor*h, factor*w)`` in fine pixels.
    """
    b, _, h, w = flow.shape
    weights = logits.view(b, 1, 9, factor, factor, h, w).softmax(dim=2)
    neighbours = F.unfold(factor * flow, kernel_size=3, padding=1).view(b, 2, 9, 1, 1, h, w)
    fine = (weights * neighbours).sum(dim=2)  # (b, 2, factor, factor, h, w)
    return fine.permute(0, 1, 4, 2, 5, 3).reshape(b, 2, factor * h, factor * w)


def bilinear_upsample(flow: torch.Tensor, factor: int = 8) -> torch.Tensor:
    """Bilinear upsampling of a flow field (corner-aligned), scaling its vectors by ``factor``.

    Shape: ``(B, 2, h, w)`` -> ``(B, 2, factor*h, factor*w)``.
    """
    size = (factor * flow.shape[-2], factor * flow.shape[-1])
    return factor * F.interpolate(flow, size=size, mode="bilinear", align_corners=True)


# ---------------------------------------------------------------------------------------------
# The network
# ---------------------------------------------------------------------------------------------

class RAFT(nn.Module):
    """RAFT (or RAFT-small, after ``config``) on normalised frames whose size is a multiple of 8.

    Use :class:`RAFTModel` (``get_model("raft")``) for frames in the package's convention.
    """

    #: Refinement steps where ``iters`` is None.
    default_iters: int = DEFAULT_ITERS

    def __init__(self, config: RAFTConfig = RAFT_FULL):
        super().__init__()
        self.config = config
        self.fnet = Encoder(config.feature_dim, "instance", config.small)
        self.cnet = Encoder(config.hidden_dim + config.context_dim,
                            "none" if config.small else "batch", config.small)
        self.update_block = UpdateBlock(config)

    def forward(self, image1: torch.Tensor, image2: torch.Tensor, iters: Optional[int] = None,
                detach_flow: bool = True, gradient_checkpointing: bool = False,
                amp: bool = False) -> torch.Tensor:
        """Flow from ``image1`` to ``image2`` after ``iters`` refinement steps.

        Args:
            image1, image2: ``(B, 3, H, W)`` RGB in ``[-1, 1]``, ``H`` and ``W`` multiples of 8.
            iters: refinement steps (None: :attr:`default_iters`).
            detach_flow: cut the gradient along the chain of flow estimates between steps, as in
                the authors' training; gradients still reach the images through the correlation
                volume and the context features.
            gradient_checkpointing: recompute each step in the backward pass instead of keeping
                its activations.
            amp: ``bf16``/``fp16`` (``True``: fp16): the encoders and the update operator under
                autocast, as the authors' code with ``mixed_precision``; the correlation
                volume, its lookup and the flow stay in float32.

        Returns:
            ``(B, 2, H, W)`` flow in pixels.
        """
        return self._run(image1, image2, iters, detach_flow, gradient_checkpointing,
                         every_step=False, amp=amp)[-1]

    def flow_sequence(self, image1: torch.Tensor, image2: torch.Tensor,
                      iters: Optional[int] = None, detach_flow: bool = True,
                      gradient_checkpointing: bool = False, amp: bool = False) -> list[torch.Tensor]:
        """The upsampled flow after every refinement step, as RAFT's sequence loss needs.

        Arguments as :meth:`forward`. Returns ``iters`` tensors ``(B, 2, H, W)`` in pixels; the
        last one is what :meth:`forward` returns.
        """
        return self._run(image1, image2, iters, detach_flow, gradient_checkpointing,
                         every_step=True, amp=amp)

    def _run(self, image1, image2, iters, detach_flow, gradient_checkpointing,
             every_step: bool, amp: bool = False) -> list[torch.Tensor]:
        cfg = self.config
        b = image1.shape[0]
        iters = self.default_iters if iters is None else iters
        amp = autocast_mode(amp, image1)
        with mixed_precision(amp):
            fmaps = self.fnet(torch.cat([image1, image2], dim=0))
        fmaps = fmaps.float()
        corr = CorrelationPyramid(fmaps[:b], fmaps[b:], cfg.corr_levels, cfg.corr_radius)

        with mixed_precision(amp):
            hidden, context = self.cnet(image1).split([cfg.hidden_dim, cfg.context_dim], dim=1)
            hidden, context = torch.tanh(hidden), F.relu(context)
            features = self._step_features(context)

        # coords0: every working-resolution pixel; coords1: where it is estimated to be in frame 2.
        h, w = fmaps.shape[-2:]
        coords0 = coords_grid(b, h, w, fmaps.device, fmaps.dtype)
        coords1 = coords0

        step = partial(self._refine, corr, amp=amp)
        use_recompute = gradient_checkpointing and torch.is_grad_enabled()
        flows = []
        for i in range(iters):
            if detach_flow:
                coords1 = coords1.detach()
            if use_recompute:
                hidden, delta = recompute(step, hidden, *features, coords0, coords1,
                                          use_reentrant=False)
            else:
                hidden, delta = step(hidden, *features, coords0, coords1)
            coords1 = coords1 + delta
            if every_step or i == iters - 1:
                flows.append(self._upsample(coords1 - coords0, hidden, amp))
        if not flows:   # no refinement step: the starting flow
            flows.append(self._upsample(coords1 - coords0, hidden, amp))
        return flows

    def _upsample(self, flow: torch.Tensor, hidden: torch.Tensor, amp: bool) -> torch.Tensor:
        if self.config.small:
            return bilinear_upsample(flow)
        with mixed_precision(amp):      # the authors' update operator computes the mask
            logits = self.update_block.upsampling_weights(hidden)
        return convex_upsample(flow, logits)

    def _step_features(self, context: torch.Tensor) -> tuple:
        """What each refinement step reads besides the hidden state and the coordinates."""
        return (context,)

    def _refine(self, corr: CorrelationPyramid, hidden, context, coords0, coords1,
                amp: bool = False):
        lookup = corr.lookup(coords1)
        with mixed_precision(amp):
            return self.update_block(hidden, context, lookup, coords1 - coords0)


def coords_grid(b: int, h: int, w: int, device, dtype) -> torch.Tensor:
    """``(b, 2, h, w)`` pixel coordinates, channel 0 = x (column), channel 1 = y (row)."""
    ys, xs = torch.meshgrid(torch.arange(h, device=device, dtype=dtype),
                            torch.arange(w, device=device, dtype=dtype), indexing="ij")
    return torch.stack([xs, ys]).unsqueeze(0).expand(b, 2, h, w)


# ---------------------------------------------------------------------------------------------
# The adapter and its registration
# ---------------------------------------------------------------------------------------------

class RAFTModel(IteratedFlowModel):
    """RAFT behind the package contract: RGB in ``[0, 1]`` of any size in, flow in pixels out.

    Args:
        small: RAFT-small instead of RAFT.
        iters: refinement iterations (``None``: 12); may be changed later via :attr:`iters`.
        gradient_checkpointing: recompute the refinement steps in the backward pass.
        detach_flow: see :meth:`RAFT.forward`; ``True`` reproduces the released models' graph.

    Shape:
        image1, image2: ``(B, 3, H, W)`` RGB in ``[0, 1]`` -> ``(B, 2, H, W)`` flow in pixels.
    """

    multiple = 8
    supports_amp = True

    def __init__(self, small: bool = False, iters: Optional[int] = None,
                 gradient_checkpointing: bool = False, detach_flow: bool = True):
        super().__init__()
        config = RAFT_SMALL if small else RAFT_FULL
        self.architecture = "raft-small" if small else "raft"
        self._setup(RAFT(config), iters, DEFAULT_ITERS, gradient_checkpointing, detach_flow)
        # Every pyramid level needs at least one pixel: 8 * 2^(levels - 1) input pixels.
        self.min_size = 8 * 2 ** (config.corr_levels - 1)

    def flow_sequence(self, image1: torch.Tensor, image2: torch.Tensor) -> list[torch.Tensor]:
        """The flow after every refinement step (for RAFT's sequence loss in training).

        Shape: image1, image2 ``(B, 3, H, W)`` RGB in ``[0, 1]`` -> :attr:`iters` tensors
        ``(B, 2, H, W)`` in pixels, the last one equal to ``model(image1, image2)``.
        """
        padder = self.padder(image1.shape[-2], image1.shape[-1])
        x1 = self.normalize(padder.pad(image1))
        x2 = self.normalize(padder.pad(image2))
        flows = self.network.flow_sequence(x1, x2, iters=self.iters, detach_flow=self.detach_flow,
                                           gradient_checkpointing=self.gradient_checkpointing,
                                           amp=self.precision)
        return [padder.unpad(f) for f in flows]


#: The authors' archive of all five released checkpoints (``models/<name>.pth`` inside).
RAFT_RELEASE_URL = "https://dl.dropboxusercontent.com/s/4j4z58wuv8o0mfz/models.zip"

# The paper's configuration runs RAFT without mixed precision (its raft_config.json).
register_model(ModelSpec(
    name="raft", build=partial(RAFTModel, small=False), default_checkpoint="raft-sintel",
    description="RAFT (Teed and Deng, ECCV 2020), 5.3M parameters", mixed_precision=True))
register_model(ModelSpec(
    name="raft-small", build=partial(RAFTModel, small=True), default_checkpoint="raft-small",
    description="RAFT-small (Teed and Deng, ECCV 2020), 1.0M parameters", mixed_precision=True))

for _name, _description in [
        ("raft-chairs", "RAFT trained on FlyingChairs"),
        ("raft-things", "RAFT trained on FlyingChairs, then FlyingThings3D"),
        ("raft-sintel", "RAFT fine-tuned on Sintel (with Things, HD1K, KITTI)"),
        ("raft-kitti", "RAFT fine-tuned on KITTI 2015")]:
    register_checkpoint(CheckpointSpec(_name, "raft", _description, url=RAFT_RELEASE_URL,
                                       member=f"models/{_name}.pth"))
register_checkpoint(CheckpointSpec(
    "raft-small", "raft-small", "RAFT-small trained on FlyingChairs, then FlyingThings3D",
    url=RAFT_RELEASE_URL, member="models/raft-small.pth",
    sha256="c7d41b9cc88442bb8aa911dbb33086dac55a226394b142937ff22d5578717332"))
