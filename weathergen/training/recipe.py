"""RAFT's training recipe (Teed and Deng, ECCV 2020), the protocol the paper retrains RAFT with.

- loss: the *sequence loss*, an L1 distance to the ground truth summed over the flow after every
  refinement step, step ``i`` of ``N`` weighted ``gamma ** (N - i - 1)`` (later steps count
  more), over pixels whose flow is valid and shorter than ``max_flow``;
- optimiser: AdamW (``eps = 1e-8``) with a one-cycle learning-rate schedule (5 % linear warm-up,
  then linear decay) over the planned steps;
- gradients clipped to a norm of 1;
- batch-norm statistics frozen when fine-tuning (full RAFT's context encoder; RAFT-small has none);
- data: random crops (368 x 768 in the Sintel stage) and flips.

The authors' Sintel stage uses batches of 6, learning rate 1.25e-4, weight decay 1e-5,
``gamma = 0.85`` and 12 iterations for 100k steps; :func:`raft_optimizer` takes these as arguments so
that a short run can scale them down.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import nn

from ..errors import ConfigError

#: The Sintel stage of RAFT's published training (``train_standard.sh``).
SINTEL_STAGE = dict(lr=1.25e-4, weight_decay=1e-5, batch_size=6, crop=(368, 768), gamma=0.85,
                    iters=12, steps=100_000)


def sequence_loss(flows: Sequence[torch.Tensor], target: torch.Tensor,
                  valid: Optional[torch.Tensor] = None, gamma: float = 0.8,
                  max_flow: float = 400.0) -> torch.Tensor:
    """RAFT's sequence loss.

    Shape: flows ``N`` x ``(B, 2, H, W)`` (the estimate after each step), target ``(B, 2, H, W)``,
    valid ``(B, 1, H, W)`` bool (or ``None``: every pixel) -> a scalar.
    Each step's loss is the mean over all pixels of ``valid * |flow - target|_1`` (per channel),
    as in the authors' code; pixels whose target is ``max_flow`` pixels or longer are left out.
    """
    if not flows:
        raise ConfigError("sequence loss needs at least one flow estimate")
    if not 0.0 < gamma <= 1.0:
        raise ConfigError(f"gamma {gamma!r}: must lie in (0, 1]")
    keep = target.norm(dim=1, keepdim=True) < max_flow
    if valid is not None:
        keep = keep & valid.bool()
    weight = keep.to(target.dtype)
    n = len(flows)
    total = target.new_zeros(())
    for i, flow in enumerate(flows):
        total = total + gamma ** (n - i - 1) * (weight * (flow - target).abs()).mean()
    return total


def end_point_error(flow: torch.Tensor, target: torch.Tensor,
                    valid: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Mean Euclidean distance over valid pixels. Shape: ``(B, 2, H, W)`` twice -> scalar."""
    epe = (flow - target).norm(dim=1, keepdim=True)
    if valid is None:
        return epe.mean()
    return epe[valid.bool()].mean()


def raft_optimizer(model: nn.Module, steps: int, lr: float = SINTEL_STAGE["lr"],
                   weight_decay: float = SINTEL_STAGE["weight_decay"], pct_start: float = 0.05
                   ) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
    """AdamW and the one-cycle schedule of RAFT's training for a run of ``steps`` steps.

    As in the authors' code the schedule is laid out over ``steps + 100`` steps, so the learning
    rate has not reached zero at the last step.
    """
    if steps < 1:
        raise ConfigError(f"steps {steps!r}: must be at least 1")
    params = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=lr, weight_decay=weight_decay, eps=1e-8)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(
        optimizer, max_lr=lr, total_steps=steps + 100, pct_start=pct_start,
        cycle_momentum=False, anneal_strategy="linear")
    return optimizer, scheduler


def freeze_batch_norm(model: nn.Module) -> nn.Module:
    """Keep every batch-norm layer in evaluation mode (fixed statistics), as RAFT's fine-tuning
    stages do; call after ``model.train()``."""
    for module in model.modules():
        if isinstance(module, nn.modules.batchnorm._BatchNorm):
            module.eval()
    return model


def train_step(model, optimizer, scheduler, image1: torch.Tensor, image2: torch.Tensor,
               flow: torch.Tensor, valid: Optional[torch.Tensor] = None, *, gamma: float = 0.8,
               clip: float = 1.0) -> dict:
    """One optimisation step of a model with a ``flow_sequence(image1, image2)`` method.

    Shape: images ``(B, 3, H, W)`` in ``[0, 1]``, flow ``(B, 2, H, W)``, valid ``(B, 1, H, W)``.
    Returns ``{"loss": float, "epe": float}`` (the EPE of the last estimate).
    """
    optimizer.zero_grad(set_to_none=True)
    flows = model.flow_sequence(image1, image2)
    loss = sequence_loss(flows, flow, valid, gamma=gamma)
    loss.backward()
    nn.utils.clip_grad_norm_(model.parameters(), clip)
    optimizer.step()
    scheduler.step()
    with torch.no_grad():
        epe = end_point_error(flows[-1], flow, valid)
    return {"loss": float(loss.detach()), "epe": float(epe)}


__all__ = ["SINTEL_STAGE", "end_point_error", "freeze_batch_norm", "raft_optimizer",
           "sequence_loss", "train_step"]
