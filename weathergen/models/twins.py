"""The first two stages of Twins-SVT-large (Chu et al., NeurIPS 2021), as FlowFormer's image encoder.

Twins-SVT is a vision transformer whose blocks alternate between two kinds of spatial attention:

- **locally-grouped self-attention** (LSA): attention within non-overlapping 7x7 windows;
- **global sub-sampled attention** (GSA): every token attends to a coarse summary of the whole
  map, made by a strided convolution (stride ``sr``) and a layer norm.

Each stage starts with a patch embedding (a strided convolution and a layer norm) and adds a
position-encoding generator (a depth-wise 3x3 convolution with a shortcut) after its first block.
FlowFormer keeps the first two stages of the large model (128 channels at 1/4 of the input size,
then 256 at 1/8) and takes their output as an image feature map.

Parameter names follow the layout of the ``timm`` implementation FlowFormer was trained with
(``svt.patch_embeds.0.proj.weight``, ``svt.blocks.1.0.attn.qkv.weight``, ...), including the final
layer norm of the full model (``svt.norm``, 1024 channels), which the two-stage encoder never
applies but which FlowFormer's checkpoints hold. This is our own code; ``timm`` is not needed.

Shapes: ``B`` batch, ``N = h*w`` tokens of a ``h x w`` map, ``C`` channels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

#: Twins-SVT-large: channels, heads, blocks, window size and sub-sampling ratio of each stage.
EMBED_DIMS = (128, 256, 512, 1024)
NUM_HEADS = (4, 8, 16, 32)
DEPTHS = (2, 2, 18, 2)
WINDOW = 7
SR_RATIOS = (8, 4, 2, 1)
#: Stages FlowFormer uses.
STAGES = 2


def window_partition(x: torch.Tensor, ws: int) -> tuple[torch.Tensor, int, int]:
    """Split ``(B, h, w, C)`` into ``ws x ws`` windows, zero-padding right and bottom.

    Returns ``(B, nh, nw, ws*ws, C)`` (tokens of a window in row-major order), ``nh``, ``nw``.
    """
    b, h, w, c = x.shape
    x = F.pad(x, (0, 0, 0, (-w) % ws, 0, (-h) % ws))
    nh, nw = x.shape[1] // ws, x.shape[2] // ws
    x = x.view(b, nh, ws, nw, ws, c).transpose(2, 3)
    return x.reshape(b, nh, nw, ws * ws, c), nh, nw


def window_merge(x: torch.Tensor, ws: int, h: int, w: int) -> torch.Tensor:
    """Inverse of :func:`window_partition`: ``(B, nh, nw, ws*ws, C)`` -> ``(B, h, w, C)``."""
    b, nh, nw, _, c = x.shape
    x = x.view(b, nh, nw, ws, ws, c).transpose(2, 3).reshape(b, nh * ws, nw * ws, c)
    return x[:, :h, :w]


def split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """``(..., L, heads*d)`` -> ``(..., heads, L, d)``."""
    return x.unflatten(-1, (heads, -1)).transpose(-3, -2)


def merge_heads(x: torch.Tensor) -> torch.Tensor:
    """``(..., heads, L, d)`` -> ``(..., L, heads*d)``."""
    return x.transpose(-3, -2).flatten(-2)


class LocallyGroupedAttention(nn.Module):
    """Multi-head self-attention within ``ws x ws`` windows (LSA).

    Shape: ``(B, N, C)`` tokens of a ``size = (h, w)`` map -> ``(B, N, C)``.
    """

    def __init__(self, dim: int, heads: int, ws: int):
        super().__init__()
        self.heads, self.ws = heads, ws
        self.qkv = nn.Linear(dim, 3 * dim)  # output channels ordered (q|k|v, head, d)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        b, n, c = x.shape
        h, w = size
        windows, nh, nw = window_partition(x.view(b, h, w, c), self.ws)
        q, k, v = (split_heads(t, self.heads) for t in self.qkv(windows).chunk(3, dim=-1))
        out = merge_heads(F.scaled_dot_product_attention(q, k, v))
        return self.proj(window_merge(out, self.ws, h, w).reshape(b, n, c))


class GlobalSubsampledAttention(nn.Module):
    """Multi-head attention of every token over a sub-sampled copy of the map (GSA).

    Shape: ``(B, N, C)`` tokens of a ``size = (h, w)`` map -> ``(B, N, C)``.
    """

    def __init__(self, dim: int, heads: int, sr_ratio: int):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)  # output channels ordered (k|v, head, d)
        self.proj = nn.Linear(dim, dim)
        self.sr = self.norm = None
        if sr_ratio > 1:
            self.sr = nn.Conv2d(dim, dim, sr_ratio, stride=sr_ratio)
            self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        b, n, c = x.shape
        q = split_heads(self.q(x), self.heads)
        summary = x
        if self.sr is not None:
            summary = self.sr(x.transpose(1, 2).reshape(b, c, *size)).flatten(2).transpose(1, 2)
            summary = self.norm(summary)
        k, v = (split_heads(t, self.heads) for t in self.kv(summary).chunk(2, dim=-1))
        return self.proj(merge_heads(F.scaled_dot_product_attention(q, k, v)))


class Mlp(nn.Module):
    """``fc2(gelu(fc1(x)))`` with a hidden width of ``ratio * dim``."""

    def __init__(self, dim: int, ratio: int = 4):
        super().__init__()
        self.fc1 = nn.Linear(dim, ratio * dim)
        self.fc2 = nn.Linear(ratio * dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class TwinsBlock(nn.Module):
    """Pre-norm transformer block: ``x + attn(norm1(x))``, then ``x + mlp(norm2(x))``."""

    def __init__(self, dim: int, heads: int, ws: int, sr_ratio: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = (GlobalSubsampledAttention(dim, heads, sr_ratio) if ws == 1
                     else LocallyGroupedAttention(dim, heads, ws))
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim)

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        x = x + self.attn(self.norm1(x), size)
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    """Non-overlapping ``patch x patch`` patches to tokens: a strided convolution, a layer norm.

    Shape: ``(B, C_in, H, W)`` -> ``(B, (H/patch)*(W/patch), dim)`` and ``(H/patch, W/patch)``.
    """

    def __init__(self, in_chans: int, dim: int, patch: int):
        super().__init__()
        self.proj = nn.Conv2d(in_chans, dim, patch, stride=patch)
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        x = self.proj(x)
        size = (x.shape[-2], x.shape[-1])
        return self.norm(x.flatten(2).transpose(1, 2)), size


class PosConv(nn.Module):
    """Position-encoding generator: ``x + depthwise_conv3x3(x)`` on the token map."""

    def __init__(self, dim: int):
        super().__init__()
        self.proj = nn.Sequential(nn.Conv2d(dim, dim, 3, padding=1, groups=dim))

    def forward(self, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        b, n, c = x.shape
        grid = x.transpose(1, 2).reshape(b, c, *size)
        return (self.proj(grid) + grid).flatten(2).transpose(1, 2)


class TwinsStages(nn.Module):
    """The first :data:`STAGES` stages of Twins-SVT-large, in ``timm``'s parameter layout."""

    def __init__(self):
        super().__init__()
        self.patch_embeds = nn.ModuleList()
        self.blocks = nn.ModuleList()
        self.pos_block = nn.ModuleList()
        in_chans, patch = 3, 4
        for stage in range(STAGES):
            dim = EMBED_DIMS[stage]
            self.patch_embeds.append(PatchEmbed(in_chans, dim, patch))
            self.blocks.append(nn.ModuleList(
                TwinsBlock(dim, NUM_HEADS[stage], 1 if i % 2 else WINDOW, SR_RATIOS[stage])
                for i in range(DEPTHS[stage])))
            self.pos_block.append(PosConv(dim))
            in_chans, patch = dim, 2
        # Final norm of the full four-stage model: in the checkpoints, never applied here.
        self.norm = nn.LayerNorm(EMBED_DIMS[-1], eps=1e-6)


class TwinsEncoder(nn.Module):
    """Image features from the first two stages of Twins-SVT-large.

    Shape: ``(B, 3, H, W)`` normalised RGB, ``H`` and ``W`` multiples of 8 and at least 32 ->
    ``(B, 256, H/8, W/8)``.
    """

    def __init__(self):
        super().__init__()
        self.svt = TwinsStages()
        for m in self.modules():  # timm's initialisation (matters for untrained models only)
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)

    def forward(self, x: torch.Tensor, gradient_checkpointing: bool = False) -> torch.Tensor:
        b = x.shape[0]
        svt = self.svt
        for embed, blocks, pos_block in zip(svt.patch_embeds, svt.blocks, svt.pos_block):
            x, size = embed(x)
            for j, block in enumerate(blocks):
                if gradient_checkpointing and torch.is_grad_enabled():
                    x = recompute(block, x, size, use_reentrant=False)
                else:
                    x = block(x, size)
                if j == 0:
                    x = pos_block(x, size)
            x = x.transpose(1, 2).reshape(b, -1, *size)
        return x
