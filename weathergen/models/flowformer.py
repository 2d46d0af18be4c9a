"""FlowFormer: a transformer architecture for optical flow (Huang et al., ECCV 2022).

The network, in the paper's parts (one section each below):

1. **Image encoders** (paper Sec. 3.1): the first two stages of Twins-SVT-large
   (:mod:`weathergen.models.twins`) give 256-channel features at 1/8 resolution, once for both
   frames (followed by a 1x1 convolution; these are correlated) and once, with separate weights,
   for frame 1 alone (the context).
2. **Cost volume encoder** (Sec. 3.2): the dot products of every frame-1 feature with every
   frame-2 feature form one ``h x w`` cost map per frame-1 pixel. Each cost map is cut into 8x8
   patches by three strided convolutions and summarised, by cross-attention, into 8 latent
   tokens ("cost memory"); three rounds of self-attention among a pixel's tokens, each followed by
   attention across pixels (Twins-style local and global blocks whose queries and keys also see
   the context features), refine the memory.
3. **Cost memory decoder** (Sec. 3.3): at every refinement step, the cost values in a 9x9 window
   around each pixel's current match become a query that attends to that pixel's cost memory
   (with a sinusoidal encoding of the match position); both feed a GMA update operator
   (:mod:`weathergen.models.gma`) that predicts a residual flow. The flow at 1/8 resolution is
   upsampled by RAFT's learned convex combination.

Module and parameter names follow the checkpoints the authors released (``sintel.pth`` and
siblings, saved from ``DataParallel`` with a ``module.`` prefix), so those files load as they are.
A few constants of the trained model are reproduced as they are: the cost volume is not scaled by
``1/sqrt(D)``, the sinusoidal position encodings use ``3.14`` for pi and positions divided by 200,
and padded positions in the attention windows take part in the attention (with zero features and
their position encoding).

Shapes below: ``B`` batch, ``H, W`` padded input size, ``h = H/8, w = W/8`` the working resolution,
``K = 8`` latent tokens per pixel.
"""

from __future__ import annotations

from functools import partial
from typing import Optional

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from .base import IteratedFlowModel, in_float32
from .checkpoints import CheckpointSpec
from .gma import ContextAttention, GMAUpdateBlock
from .raft import coords_grid, convex_upsample, sample_bilinear
from .registry import ModelSpec, register_checkpoint, register_model
from .twins import (TwinsEncoder, merge_heads, split_heads, window_merge, window_partition)

#: Refinement iterations when none are given: the authors' evaluation setting
#: (``configs/things_eval.py``), which the paper's attack code uses.
DEFAULT_ITERS = 32

FEATURE_DIM = 256       # image features and context
COST_PATCH = 8          # cost-map patch size
COST_INPUT_DIM = 64     # channels of a cost-map patch token (before the position encoding)
LATENT_TOKENS = 8       # K
LATENT_DIM = 128        # channels of a latent cost token
ENCODER_DEPTH = 3
QUERY_DIM = 64          # channels of the decoder's cost query
CONTEXT_QK_DIM = 64     # context channels added to the queries and keys of the pixel attention
LOOKUP_RADIUS = 4       # 9x9 cost window around the current match
HEADS = 8
#: Cost maps per recomputed chunk of the cost encoder's first stage (gradient checkpointing).
SUMMARY_CHUNK = 512


def position_encoding(coords: torch.Tensor, dim: int) -> torch.Tensor:
    """FlowFormer's linear sinusoidal encoding of ``(x, y)`` positions.

    With ``f = 0, 1, ..., dim/4 - 1`` and ``a = 3.14 * f / 200`` (the trained constants):
    ``[sin(a x), cos(a x), sin(a y), cos(a y)]``.

    Shape: ``(..., 2)`` -> ``(..., dim)``.
    """
    freqs = torch.arange(dim // 4, dtype=coords.dtype, device=coords.device)
    x = 3.14 * coords[..., 0:1] * freqs / 200
    y = 3.14 * coords[..., 1:2] * freqs / 200
    return torch.cat([torch.sin(x), torch.cos(x), torch.sin(y), torch.cos(y)], dim=-1)


def _grid_positions(h: int, w: int, like: torch.Tensor, step: float = 1.0) -> torch.Tensor:
    """``(h*w, 2)`` positions ``(x, y) * step`` of a row-major ``h x w`` grid."""
    ys, xs = torch.meshgrid(torch.arange(h, dtype=like.dtype, device=like.device),
                            torch.arange(w, dtype=like.dtype, device=like.device), indexing="ij")
    return torch.stack([xs, ys], dim=-1).reshape(h * w, 2) * step


def _feed_forward(dim: int) -> nn.Sequential:
    # Indices 0 and 3 carry the weights, as in the checkpoints (dropout layers between).
    return nn.Sequential(nn.Linear(dim, dim), nn.GELU(), nn.Dropout(0.0), nn.Linear(dim, dim),
                         nn.Dropout(0.0))


# ---------------------------------------------------------------------------------------------
# 2. Cost volume encoder
# ---------------------------------------------------------------------------------------------

class CostPatchEmbed(nn.Module):
    """Cost maps to patch tokens: three stride-2 6x6 convolutions (8x8 patches), the patch centre's
    position encoding appended, a two-layer 1x1 feed-forward and a layer norm.

    Shape: ``(M, 1, h, w)`` cost maps -> ``(M, h3*w3, 128)`` tokens and ``(h3, w3)``, where
    ``h3 = ceil(h / 8)``.
    """

    def __init__(self, dim: int = COST_INPUT_DIM):
        super().__init__()
        self.dim = dim
        self.proj = nn.Sequential(
            nn.Conv2d(1, dim // 4, 6, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(dim // 4, dim // 2, 6, stride=2, padding=2), nn.ReLU(),
            nn.Conv2d(dim // 2, dim, 6, stride=2, padding=2))
        self.ffn_with_coord = nn.Sequential(nn.Conv2d(2 * dim, 2 * dim, 1), nn.ReLU(),
                                            nn.Conv2d(2 * dim, 2 * dim, 1))
        self.norm = nn.LayerNorm(2 * dim)

    def forward(self, cost_maps: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        m, _, h, w = cost_maps.shape
        x = self.proj(F.pad(cost_maps, (0, (-w) % COST_PATCH, 0, (-h) % COST_PATCH)))
        h3, w3 = x.shape[-2:]
        centres = _grid_positions(h3, w3, x, step=COST_PATCH) + COST_PATCH / 2
        pe = position_encoding(centres, self.dim).t().reshape(1, self.dim, h3, w3)
        x = self.ffn_with_coord(torch.cat([x, pe.expand(m, -1, -1, -1)], dim=1))
        return self.norm(x.flatten(2).transpose(1, 2)), (h3, w3)


class LatentCrossAttention(nn.Module):
    """The learned latent tokens attend to the patch tokens of each cost map.

    Shape: latents ``(1, K, 128)``, patch tokens ``(M, P, 128)`` -> ``(M, K, 128)``.
    """

    def __init__(self, dim: int = LATENT_DIM, token_dim: int = 2 * COST_INPUT_DIM):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(token_dim, dim)
        self.v = nn.Linear(token_dim, dim)
        self.proj = nn.Linear(dim, dim)
        self.ffn = _feed_forward(dim)

    def forward(self, latents: torch.Tensor, tokens: torch.Tensor) -> torch.Tensor:
        m = tokens.shape[0]
        q = split_heads(self.q(self.norm1(latents)), HEADS).expand(m, -1, -1, -1)
        k, v = split_heads(self.k(tokens), HEADS), split_heads(self.v(tokens), HEADS)
        x = latents + self.proj(merge_heads(F.scaled_dot_product_attention(q, k, v)))
        return x + self.ffn(self.norm2(x))


class LatentSelfAttention(nn.Module):
    """Self-attention among the K latent tokens of each pixel, then a feed-forward.

    Shape: ``(M, K, 128)`` -> ``(M, K, 128)``.
    """

    def __init__(self, dim: int = LATENT_DIM):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.q, self.k, self.v = nn.Linear(dim, dim), nn.Linear(dim, dim), nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)
        self.ffn = _feed_forward(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.norm1(x)
        q, k, v = (split_heads(f(y), HEADS) for f in (self.q, self.k, self.v))
        x = x + self.proj(merge_heads(F.scaled_dot_product_attention(q, k, v)))
        return x + self.ffn(self.norm2(x))


class _ContextMixin(nn.Module):
    """Projects the 256 context channels to the 64 that join the queries and keys."""

    def context_tokens(self, context: torch.Tensor, n: int) -> torch.Tensor:
        """``(B, 256, h, w)`` -> ``(n, h, w, 64)`` for ``n = B*K`` token maps; map ``b*K + k``
        belongs to batch element ``b`` (the latent tokens of one frame pair stay together)."""
        b, c, h, w = context.shape
        projected = self.context_proj(context.flatten(2).transpose(1, 2)).view(b, h, w, -1)
        return projected.repeat_interleave(n // b, dim=0)


class LocalContextAttention(_ContextMixin):
    """Attention within 7x7 windows of the pixel grid; queries and keys read the token, the
    projected context and the position inside the window; values read the token only.

    Shape: tokens ``(B*K, h*w, 128)``, context ``(B, 256, h, w)`` -> ``(B*K, h*w, 128)``.
    """

    def __init__(self, dim: int = LATENT_DIM, ws: int = 7):
        super().__init__()
        self.ws = ws
        self.context_proj = nn.Linear(FEATURE_DIM, CONTEXT_QK_DIM)
        self.q = nn.Linear(dim + CONTEXT_QK_DIM, dim)
        self.k = nn.Linear(dim + CONTEXT_QK_DIM, dim)
        self.v = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, size: tuple[int, int], context: torch.Tensor):
        n, _, c = x.shape
        h, w = size
        x = x.view(n, h, w, c)
        x_qk = torch.cat([x, self.context_tokens(context, n)], dim=-1)
        windows, nh, nw = window_partition(x, self.ws)
        windows_qk, _, _ = window_partition(x_qk, self.ws)
        # Positions within a window, added after padding (padded tokens get them too).
        windows_qk = windows_qk + position_encoding(
            _grid_positions(self.ws, self.ws, x), x_qk.shape[-1])
        q = split_heads(self.q(windows_qk), HEADS)
        k = split_heads(self.k(windows_qk), HEADS)
        v = split_heads(self.v(windows), HEADS)
        out = merge_heads(F.scaled_dot_product_attention(q, k, v))
        return self.proj(window_merge(out, self.ws, h, w).reshape(n, h * w, c))


class GlobalContextAttention(_ContextMixin):
    """Attention of every pixel over a 4x sub-sampled copy of the grid; queries see token, context
    and position, keys a strided convolution of token and context plus position, values a strided
    convolution of the token.

    Shape: as :class:`LocalContextAttention`.
    """

    def __init__(self, dim: int = LATENT_DIM, sr_ratio: int = 4):
        super().__init__()
        self.sr_ratio = sr_ratio
        self.context_proj = nn.Linear(FEATURE_DIM, CONTEXT_QK_DIM)
        self.q = nn.Linear(dim + CONTEXT_QK_DIM, dim)
        self.k = nn.Linear(dim, dim)
        self.v = nn.Linear(dim, dim)
        self.proj = nn.Linear(dim, dim)
        self.sr_key = nn.Conv2d(dim + CONTEXT_QK_DIM, dim, sr_ratio, stride=sr_ratio)
        self.sr_value = nn.Conv2d(dim, dim, sr_ratio, stride=sr_ratio)
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, size: tuple[int, int], context: torch.Tensor):
        n, _, c = x.shape
        h, w = size
        r = self.sr_ratio
        x = x.view(n, h, w, c)
        x_qk = torch.cat([x, self.context_tokens(context, n)], dim=-1)
        # Zero padding to a multiple of the ratio; the padded pixels are queries and feed the
        # summaries, as in the trained model.
        pad = (0, 0, 0, (-w) % r, 0, (-h) % r)
        x, x_qk = F.pad(x, pad), F.pad(x_qk, pad)
        hp, wp = x.shape[1:3]
        q = self.q(x_qk.reshape(n, hp * wp, -1)
                   + position_encoding(_grid_positions(hp, wp, x), x_qk.shape[-1]))
        keys = self.sr_key(x_qk.permute(0, 3, 1, 2)).flatten(2).transpose(1, 2)
        values = self.sr_value(x.permute(0, 3, 1, 2)).flatten(2).transpose(1, 2)
        keys = self.norm(keys) + position_encoding(
            _grid_positions(hp // r, wp // r, x, step=r), c)
        k = split_heads(self.k(keys), HEADS)
        v = split_heads(self.v(self.norm(values)), HEADS)
        out = merge_heads(F.scaled_dot_product_attention(split_heads(q, HEADS), k, v))
        out = out.view(n, hp, wp, c)[:, :h, :w].reshape(n, h * w, c)
        return self.proj(out)


class ContextBlock(nn.Module):
    """Pre-norm transformer block around a context attention (local or global)."""

    def __init__(self, attn: nn.Module, dim: int = LATENT_DIM):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = attn
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = _Mlp(dim)

    def forward(self, x, size, context):
        x = x + self.attn(self.norm1(x), size, context)
        return x + self.mlp(self.norm2(x))


class _Mlp(nn.Module):
    def __init__(self, dim: int, ratio: int = 4):
        super().__init__()
        self.fc1 = nn.Linear(dim, ratio * dim)
        self.fc2 = nn.Linear(ratio * dim, dim)

    def forward(self, x):
        return self.fc2(F.gelu(self.fc1(x)))


class PixelAttentionLayer(nn.Module):
    """Attention across pixels for each latent token index: a local block, then a global one."""

    def __init__(self):
        super().__init__()
        self.local_block = ContextBlock(LocalContextAttention())
        self.global_block = ContextBlock(GlobalContextAttention())

    def forward(self, x, size, context):
        return self.global_block(self.local_block(x, size, context), size, context)


class CostPerceiverEncoder(nn.Module):
    """Cost maps to cost memory: patch tokens -> K latent tokens -> 3 x (attention among a pixel's
    tokens, attention across pixels) -> plus the latent tokens before those rounds.

    Shape: cost maps ``(B*h*w, 1, h, w)``, context ``(B, 256, h, w)`` -> ``(B*h*w, K, 128)``.
    """

    def __init__(self):
        super().__init__()
        self.patch_embed = CostPatchEmbed()
        self.latent_tokens = nn.Parameter(torch.randn(1, LATENT_TOKENS, LATENT_DIM))
        self.input_layer = LatentCrossAttention()
        self.encoder_layers = nn.ModuleList(LatentSelfAttention() for _ in range(ENCODER_DEPTH))
        self.vertical_encoder_layers = nn.ModuleList(PixelAttentionLayer()
                                                     for _ in range(ENCODER_DEPTH))

    def forward(self, cost_maps: torch.Tensor, context: torch.Tensor,
                gradient_checkpointing: bool = False) -> torch.Tensor:
        b, _, h, w = context.shape
        k = LATENT_TOKENS
        run = _runner(gradient_checkpointing)
        if gradient_checkpointing and torch.is_grad_enabled():
            # The patch embedding's activations are the largest of the network (about 5 GiB
            # for a Sintel frame): recompute them in chunks of cost maps, one at a time.
            x = torch.cat([run(self._summarise, chunk)
                           for chunk in cost_maps.split(SUMMARY_CHUNK)], dim=0)
        else:
            x = self._summarise(cost_maps)
        shortcut = x
        for attend_tokens, attend_pixels in zip(self.encoder_layers,
                                                self.vertical_encoder_layers):
            x = run(attend_tokens, x)
            # (B*h*w, K, D) -> (B*K, h*w, D): one token map per latent index.
            x = x.view(b, h * w, k, -1).transpose(1, 2).reshape(b * k, h * w, -1)
            x = run(attend_pixels, x, (h, w), context)
            x = x.view(b, k, h * w, -1).transpose(1, 2).reshape(b * h * w, k, -1)
        return x + shortcut

    def _summarise(self, cost_maps: torch.Tensor) -> torch.Tensor:
        tokens, _ = self.patch_embed(cost_maps)
        return self.input_layer(self.latent_tokens, tokens)


def _runner(gradient_checkpointing: bool):
    """``run(fn, *args)`` calls ``fn(*args)``, recomputed in the backward pass when
    ``gradient_checkpointing`` is on (and gradients are being recorded)."""
    def run(fn, *args):
        if gradient_checkpointing and torch.is_grad_enabled():
            return recompute(fn, *args, use_reentrant=False)
        return fn(*args)
    return run


class MemoryEncoder(nn.Module):
    """Image features of both frames, their cost volume, and the cost memory."""

    def __init__(self):
        super().__init__()
        self.feat_encoder = TwinsEncoder()
        self.channel_convertor = nn.Conv2d(FEATURE_DIM, FEATURE_DIM, 1, bias=False)
        self.cost_perceiver_encoder = CostPerceiverEncoder()

    def forward(self, image1: torch.Tensor, image2: torch.Tensor, context: torch.Tensor,
                gradient_checkpointing: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """Shape: images ``(B, 3, H, W)``, context ``(B, 256, h, w)`` -> cost maps
        ``(B*h*w, 1, h, w)`` (map ``i`` holds ``<f1(i), f2(j)>`` for every frame-2 pixel ``j``;
        not scaled) and cost memory ``(B*h*w, K, 128)``."""
        b = image1.shape[0]
        feats = self.feat_encoder(torch.cat([image1, image2], dim=0), gradient_checkpointing)
        feats = self.channel_convertor(feats)
        f1, f2 = feats[:b], feats[b:]
        _, _, h, w = f1.shape
        cost_maps = cost_volume(f1, f2).reshape(b * h * w, 1, h, w)
        return cost_maps, self.cost_perceiver_encoder(cost_maps, context, gradient_checkpointing)


# ---------------------------------------------------------------------------------------------
# 3. Cost memory decoder
# ---------------------------------------------------------------------------------------------

@in_float32
def cost_volume(f1: torch.Tensor, f2: torch.Tensor) -> torch.Tensor:
    """Every dot product of a frame-1 and a frame-2 feature vector, in float32.
    Shape: ``(B, C, h, w)`` x2 -> ``(B, h*w, h*w)``."""
    return torch.matmul(f1.flatten(2).transpose(1, 2), f2.flatten(2))


@in_float32
def cost_window(cost_maps: torch.Tensor, coords: torch.Tensor, radius: int) -> torch.Tensor:
    """Cost values in a ``(2r+1)^2`` window around each pixel's current match, bilinearly sampled
    (zero outside the map); channel ``a*(2r+1) + b`` is the offset ``(a - r, b - r)`` in
    ``(x, y)``, the x offset varying slowest (as trained).

    Shape: cost maps ``(B*h*w, 1, h, w)``, coords ``(B, 2, h, w)`` (match positions ``(x, y)`` in
    frame 2) -> ``(B, (2r+1)^2, h, w)``.
    """
    b, _, h, w = coords.shape
    steps = torch.arange(-radius, radius + 1, dtype=coords.dtype, device=coords.device)
    offsets = torch.stack([steps.repeat_interleave(2 * radius + 1),
                           steps.repeat(2 * radius + 1)], dim=-1).view(1, -1, 1, 2)
    centres = coords.permute(0, 2, 3, 1).reshape(b * h * w, 1, 1, 2)
    values = sample_bilinear(cost_maps, centres + offsets)  # (B*h*w, 1, (2r+1)^2, 1)
    return values.view(b, h, w, -1).permute(0, 3, 1, 2)


class CostQueryAttention(nn.Module):
    """A pixel's cost query, with the encoded match position, attends to its cost memory.

    Keys and values are computed once per frame pair (:meth:`keys_values`).

    Shape: query ``(M, 1, 64)``, keys/values ``(M, heads, K, 64/heads)``, coords ``(B, 2, h, w)``
    with ``M = B*h*w`` -> ``(M, 1, 64)``.
    """

    def __init__(self, dim: int = QUERY_DIM, memory_dim: int = LATENT_DIM):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.q = nn.Linear(dim, dim)
        self.k = nn.Linear(memory_dim, dim)
        self.v = nn.Linear(memory_dim, dim)
        self.proj = nn.Linear(2 * dim, dim)  # reads the attention output and the query
        self.ffn = _feed_forward(dim)

    def keys_values(self, memory: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return split_heads(self.k(memory), HEADS), split_heads(self.v(memory), HEADS)

    def forward(self, query: torch.Tensor, keys: torch.Tensor, values: torch.Tensor,
                coords: torch.Tensor) -> torch.Tensor:
        position = position_encoding(coords.permute(0, 2, 3, 1).reshape(-1, 1, 2),
                                     query.shape[-1])
        q = split_heads(self.q(self.norm1(query) + position), HEADS)
        x = merge_heads(F.scaled_dot_product_attention(q, keys, values))
        x = query + self.proj(torch.cat([x, query], dim=-1))
        return x + self.ffn(self.norm2(x))


class _DecoderLayer(nn.Module):
    def __init__(self):
        super().__init__()
        self.cross_attend = CostQueryAttention()


class MemoryDecoder(nn.Module):
    """Iterative refinement reading the cost volume locally and the cost memory globally."""

    def __init__(self):
        super().__init__()
        self.flow_token_encoder = nn.Sequential(
            nn.Conv2d((2 * LOOKUP_RADIUS + 1) ** 2, QUERY_DIM, 1), nn.GELU(),
            nn.Conv2d(QUERY_DIM, QUERY_DIM, 1))
        self.proj = nn.Conv2d(FEATURE_DIM, FEATURE_DIM, 1)
        self.decoder_layer = _DecoderLayer()
        self.update_block = GMAUpdateBlock(QUERY_DIM + (2 * LOOKUP_RADIUS + 1) ** 2)
        self.att = ContextAttention(128, dim_head=128, max_pos=160)

    def forward(self, cost_maps: torch.Tensor, memory: torch.Tensor, context: torch.Tensor,
                iters: int, detach_flow: bool = True,
                gradient_checkpointing: bool = False) -> torch.Tensor:
        """Shape: cost maps ``(B*h*w, 1, h, w)``, memory ``(B*h*w, K, 128)``, context
        ``(B, 256, h, w)`` -> flow ``(B, 2, 8h, 8w)`` in pixels."""
        b, _, h, w = context.shape
        hidden, inp = self.proj(context).split([128, 128], dim=1)
        hidden, inp = torch.tanh(hidden), F.relu(inp)
        attention = self.att(inp)
        keys, values = self.decoder_layer.cross_attend.keys_values(memory)

        coords0 = coords_grid(b, h, w, context.device, context.dtype)
        coords1 = coords0
        run = _runner(gradient_checkpointing)
        step = partial(self._refine, cost_maps)
        for _ in range(iters):
            if detach_flow:
                coords1 = coords1.detach()
            hidden, delta = run(step, hidden, inp, attention, keys, values, coords0, coords1)
            coords1 = coords1 + delta
        return convex_upsample(coords1 - coords0, self.update_block.upsampling_weights(hidden))

    def _refine(self, cost_maps, hidden, inp, attention, keys, values, coords0, coords1):
        window = cost_window(cost_maps, coords1, LOOKUP_RADIUS)
        b, _, h, w = window.shape
        query = self.flow_token_encoder(window).permute(0, 2, 3, 1).reshape(b * h * w, 1, -1)
        cost_global = self.decoder_layer.cross_attend(query, keys, values, coords1)
        cost_global = cost_global.view(b, h, w, -1).permute(0, 3, 1, 2)
        corr = torch.cat([cost_global, window], dim=1)
        return self.update_block(hidden, inp, corr, coords1 - coords0, attention)


# ---------------------------------------------------------------------------------------------
# The network
# ---------------------------------------------------------------------------------------------

class FlowFormer(nn.Module):
    """FlowFormer on normalised frames whose size is a multiple of 8 (at least 32).

    Use :class:`FlowFormerModel` (``get_model("flowformer")``) for frames in the package's
    convention.
    """

    def __init__(self):
        super().__init__()
        self.memory_encoder = MemoryEncoder()
        self.memory_decoder = MemoryDecoder()
        self.context_encoder = TwinsEncoder()

    def forward(self, image1: torch.Tensor, image2: torch.Tensor, iters: int = DEFAULT_ITERS,
                detach_flow: bool = True, gradient_checkpointing: bool = False) -> torch.Tensor:
        """Flow from ``image1`` to ``image2``.

        Args:
            image1, image2: ``(B, 3, H, W)`` RGB in ``[-1, 1]``.
            iters: refinement steps of the decoder.
            detach_flow: cut the gradient along the chain of flow estimates, as trained.
            gradient_checkpointing: recompute the transformer blocks, the cost encoder's stages
                and every refinement step in the backward pass instead of keeping their
                activations.

        Returns:
            ``(B, 2, H, W)`` flow in pixels.
        """
        context = self.context_encoder(image1, gradient_checkpointing)
        cost_maps, memory = self.memory_encoder(image1, image2, context, gradient_checkpointing)
        return self.memory_decoder(cost_maps, memory, context, iters, detach_flow,
                                   gradient_checkpointing)


# ---------------------------------------------------------------------------------------------
# The adapter and its registration
# ---------------------------------------------------------------------------------------------

class FlowFormerModel(IteratedFlowModel):
    """FlowFormer behind the package contract: RGB in ``[0, 1]`` of any size in, flow out.

    The whole (padded) frame is processed at once, as the paper's attack code does; the
    authors' tiled evaluation (overlapping 432x960 crops) is not used.

    Args:
        iters: decoder iterations (``None``: 32, the authors' evaluation setting).
        gradient_checkpointing: recompute activations in the backward pass (less memory).
        detach_flow: cut the gradient along the chain of flow estimates, as trained.

    Shape:
        image1, image2: ``(B, 3, H, W)`` RGB in ``[0, 1]`` -> ``(B, 2, H, W)`` flow in pixels.
    """

    architecture = "flowformer"
    multiple = 8
    # Twins' global attention sub-samples 1/4-resolution maps by 8: at least 32 input pixels.
    min_size = 32

    def __init__(self, iters: Optional[int] = None, gradient_checkpointing: bool = False,
                 detach_flow: bool = True):
        super().__init__()
        self._setup(FlowFormer(), iters, DEFAULT_ITERS, gradient_checkpointing, detach_flow)


#: The authors share their checkpoints in a Google Drive folder (no direct download address).
FLOWFORMER_RELEASE_PAGE = \
    "https://drive.google.com/drive/folders/1K2dcWxaqOLiQ3PoqRdokrgWsGIf3yBA_"

# bf16's flow measured beyond the bound on the demo (speed/bench_precision.py): refused.
register_model(ModelSpec(
    name="flowformer", build=FlowFormerModel, default_checkpoint="flowformer-sintel",
    description="FlowFormer (Huang et al., ECCV 2022), cost-volume transformer with a "
                "Twins-SVT encoder, 16.2M parameters", refused_precisions=("bf16",)))

for _stage, _description in [
        ("chairs", "FlowFormer trained on FlyingChairs"),
        ("things", "FlowFormer trained on FlyingChairs, then FlyingThings3D"),
        ("sintel", "FlowFormer fine-tuned on Sintel (with Things, HD1K, KITTI)"),
        ("kitti", "FlowFormer fine-tuned on KITTI 2015")]:
    register_checkpoint(CheckpointSpec(f"flowformer-{_stage}", "flowformer", _description,
                                       member=f"{_stage}.pth", page=FLOWFORMER_RELEASE_PAGE))
