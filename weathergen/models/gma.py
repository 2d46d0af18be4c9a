"""GMA: RAFT with Global Motion Aggregation (Jiang, Campbell, Lu, Li and Hartley, ICCV 2021).

GMA keeps RAFT's encoders, correlation pyramid, update operator and convex upsampling (imported
from :mod:`weathergen.models.raft`) and adds one module, in two parts:

1. **Attention over the context features** (paper Sec. 3.2, computed once per frame pair): every
   working-resolution pixel of frame 1 attends to every other one, with queries and keys projected
   from the context features. This says which pixels probably move together.
2. **Aggregation of motion features** (at every refinement step): the motion features of the
   update operator are projected to values and averaged with those attention weights; the result,
   scaled by a learned factor ``gamma``, is added to the local motion features. The GRU reads the
   context features, the local motion features and the aggregated ones.

Module and parameter names follow the checkpoints the authors released (``gma-things.pth`` and
siblings, saved from ``DataParallel`` with a ``module.`` prefix), so those files load as they are.
The released models were trained with the content-only attention ("GMA" in the paper, one head);
their files still hold the relative position embeddings of the paper's position variants
(``att.pos_emb.*``, including the index table ``rel_ind``), which the content-only model does not
use: the module keeps them so that the files load strictly.

Shapes below: ``B`` batch, ``H, W`` padded input size, ``h = H/8, w = W/8`` the working resolution.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import nn

from .base import IteratedFlowModel, in_float32, mixed_precision
from .checkpoints import CheckpointSpec
from .raft import (RAFT, RAFT_FULL, CorrelationPyramid, Encoder, FlowHead, MotionEncoder,
                   SepConvGRU)
from .registry import ModelSpec, register_checkpoint, register_model

#: Refinement iterations when none are given: what the paper's attack code uses for GMA (the
#: GMA authors evaluate Sintel with 32 and KITTI with 24).
DEFAULT_ITERS = 6


# ---------------------------------------------------------------------------------------------
# 1. Attention over the context features
# ---------------------------------------------------------------------------------------------

class RelativePositionEmbedding(nn.Module):
    """Learned embeddings of row and column offsets (the paper's position variants).

    Kept for the key layout of the released files: ``rel_height`` and ``rel_width`` hold one
    vector per offset in ``[-(max_pos - 1), max_pos - 1]``; ``rel_ind[i, j] = j - i + max_pos - 1``
    indexes them. The content-only GMA never calls this module.
    """

    def __init__(self, max_pos: int, dim: int):
        super().__init__()
        self.rel_height = nn.Embedding(2 * max_pos - 1, dim)
        self.rel_width = nn.Embedding(2 * max_pos - 1, dim)
        offsets = torch.arange(max_pos).view(1, -1) - torch.arange(max_pos).view(-1, 1)
        self.register_buffer("rel_ind", offsets + max_pos - 1)


class ContextAttention(nn.Module):
    """Softmax attention of every pixel over all pixels, from the context features.

    Shape: ``(B, dim, h, w)`` -> ``(B, h*w, h*w)`` attention weights (rows sum to one); row ``i``
    is the query pixel ``i`` in row-major order.
    """

    def __init__(self, dim: int = 128, dim_head: int = 128, max_pos: int = 160):
        super().__init__()
        self.scale = dim_head ** -0.5
        self.dim_head = dim_head
        self.to_qk = nn.Conv2d(dim, 2 * dim_head, 1, bias=False)
        self.pos_emb = RelativePositionEmbedding(max_pos, dim_head)

    def forward(self, context: torch.Tensor) -> torch.Tensor:
        q, k = self.to_qk(context).flatten(2).split(self.dim_head, dim=1)  # (B, d, h*w) each
        return _softmax_attention(self.scale * q, k)


@in_float32
def _softmax_attention(q: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """``softmax(qᵀ k)`` over the keys, in float32. Shape: ``(B, d, n)`` x2 -> ``(B, n, n)``."""
    return torch.matmul(q.transpose(1, 2), k).softmax(dim=-1)


# ---------------------------------------------------------------------------------------------
# 2. Aggregation of the motion features, and the update operator that reads them
# ---------------------------------------------------------------------------------------------

class MotionAggregator(nn.Module):
    """``features + gamma * (attention @ values(features))``: globally aggregated motion.

    ``gamma`` starts at zero (an untrained model behaves like RAFT) and is learned.

    Shape: attention ``(B, h*w, h*w)``, features ``(B, dim, h, w)`` -> ``(B, dim, h, w)``.
    """

    def __init__(self, dim: int = 128):
        super().__init__()
        self.to_v = nn.Conv2d(dim, dim, 1, bias=False)
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, attention: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        b, c, h, w = features.shape
        values = self.to_v(features).flatten(2).transpose(1, 2)            # (B, h*w, dim)
        aggregated = torch.matmul(attention, values).transpose(1, 2).reshape(b, c, h, w)
        return features + self.gamma * aggregated


class GMAUpdateBlock(nn.Module):
    """One refinement step: local motion features, their global aggregate, GRU, residual flow.

    Args:
        corr_channels: channels of the correlation input of the motion encoder (324 for GMA's
            4-level radius-4 lookup; FlowFormer feeds other cost features).
        hidden_dim: channels of the GRU state, the context and the motion features (128).
    """

    def __init__(self, corr_channels: int, hidden_dim: int = 128):
        super().__init__()
        self.encoder = MotionEncoder(corr_channels, small=False)
        # GRU input: context, local motion features and their aggregate.
        self.gru = SepConvGRU(hidden_dim, hidden_dim + 2 * self.encoder.out_dim)
        self.flow_head = FlowHead(hidden_dim, 256)
        self.mask = nn.Sequential(nn.Conv2d(hidden_dim, 256, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(256, 9 * 8 * 8, 1))
        self.aggregator = MotionAggregator(self.encoder.out_dim)

    def forward(self, hidden: torch.Tensor, context: torch.Tensor, corr: torch.Tensor,
                flow: torch.Tensor, attention: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Shape: hidden, context ``(B, 128, h, w)``, corr ``(B, corr_channels, h, w)``, flow
        ``(B, 2, h, w)``, attention ``(B, h*w, h*w)`` -> (new hidden, residual flow)."""
        motion = self.encoder(flow, corr)
        x = torch.cat([context, motion, self.aggregator(attention, motion)], dim=1)
        hidden = self.gru(hidden, x)
        return hidden, self.flow_head(hidden)

    def upsampling_weights(self, hidden: torch.Tensor) -> torch.Tensor:
        """Logits of the convex-upsampling weights, ``(B, 576, h, w)`` (scaled by 0.25 as
        trained)."""
        return 0.25 * self.mask(hidden)


# ---------------------------------------------------------------------------------------------
# The network
# ---------------------------------------------------------------------------------------------

class GMA(RAFT):
    """GMA on normalised frames whose size is a multiple of 8: called as
    :meth:`RAFT.forward <weathergen.models.raft.RAFT.forward>` (``iters`` None: 6). With ``amp``
    the context attention runs under autocast too, its softmax in float32.

    Use :class:`GMAModel` (``get_model("gma")``) for frames in the package's convention.
    """

    default_iters = DEFAULT_ITERS

    def __init__(self):
        nn.Module.__init__(self)       # RAFT's loop and upsampling, GMA's modules
        cfg = self.config = RAFT_FULL
        self.fnet = Encoder(cfg.feature_dim, "instance", small=False)
        self.cnet = Encoder(cfg.hidden_dim + cfg.context_dim, "batch", small=False)
        self.update_block = GMAUpdateBlock(cfg.corr_channels, cfg.hidden_dim)
        self.att = ContextAttention(cfg.context_dim, dim_head=cfg.context_dim, max_pos=160)

    def _step_features(self, context: torch.Tensor) -> tuple:
        return context, self.att(context)

    def _refine(self, corr: CorrelationPyramid, hidden, context, attention, coords0, coords1,
                amp: bool = False):
        lookup = corr.lookup(coords1)
        with mixed_precision(amp):
            return self.update_block(hidden, context, lookup, coords1 - coords0, attention)


# ---------------------------------------------------------------------------------------------
# The adapter and its registration
# ---------------------------------------------------------------------------------------------

class GMAModel(IteratedFlowModel):
    """GMA behind the package contract: RGB in ``[0, 1]`` of any size in, flow in pixels out.

    Args:
        iters: refinement iterations (``None``: 6, the paper's setting); also :attr:`iters`.
        gradient_checkpointing: recompute the refinement steps in the backward pass.
        detach_flow: cut the gradient along the chain of flow estimates, as trained.

    Shape:
        image1, image2: ``(B, 3, H, W)`` RGB in ``[0, 1]`` -> ``(B, 2, H, W)`` flow in pixels.
    """

    architecture = "gma"
    multiple = 8
    supports_amp = True

    def __init__(self, iters: Optional[int] = None, gradient_checkpointing: bool = False,
                 detach_flow: bool = True):
        super().__init__()
        self._setup(GMA(), iters, DEFAULT_ITERS, gradient_checkpointing, detach_flow)
        # Every level of the correlation pyramid needs at least one pixel.
        self.min_size = 8 * 2 ** (self.network.config.corr_levels - 1)


#: The authors keep their four checkpoints in their repository, one file each.
GMA_RELEASE_URL = "https://github.com/zacjiang/GMA/raw/2f1fd29468a86a354d44dd25d107930b3f175043/checkpoints/{}.pth"

# The paper's configuration runs GMA in mixed precision (its gma_config.json:
# "mixed_precision": true), which takes effect on CUDA.
register_model(ModelSpec(
    name="gma", build=GMAModel, default_checkpoint="gma-sintel",
    description="GMA (Jiang et al., ICCV 2021), RAFT with global motion aggregation, 5.9M "
                "parameters", mixed_precision=True, amp=True))

for _name, _description in [
        ("gma-chairs", "GMA trained on FlyingChairs"),
        ("gma-things", "GMA trained on FlyingChairs, then FlyingThings3D"),
        ("gma-sintel", "GMA fine-tuned on Sintel (with Things, HD1K, KITTI)"),
        ("gma-kitti", "GMA fine-tuned on KITTI 2015")]:
    register_checkpoint(CheckpointSpec(_name, "gma", _description,
                                       url=GMA_RELEASE_URL.format(_name)))
