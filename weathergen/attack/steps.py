"""The per-step bookkeeping of an attack loop: each evaluated step's record, a pair's outcome,
and the log of B pairs' steps with their best so far (the weather attack's, the sequence
attack's and the Lp attacks')."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch

from ..flow import aee


@dataclass
class StepRecord:
    """One evaluated step. Distances in pixels; ``robustness`` is AEE(f, f̌) against the benign
    flow; ``best_distance`` the lowest distance so far (never increases)."""

    step: int
    loss: float
    distance: float
    penalty: float
    robustness: float
    best_distance: float
    seconds: float


@dataclass
class AttackResult:
    """Outcome of :func:`attack_pair`.

    Shape: benign_flow, initial_flow, best_flow, target (1, 2, H, W) pixels, on the CPU;
    best_particles a detached CPU record (float32, not yet quantised to storage precision).
    """

    best_particles: object
    best_step: int
    history: list[StepRecord]
    benign_flow: torch.Tensor
    initial_flow: torch.Tensor
    best_flow: torch.Tensor
    target: torch.Tensor
    frozen: bool = False    # True when no variable could influence the loss (nothing visible)
    #: a stereo sequence attack's second camera: its benign, initial and best flows (float frames)
    second: Optional[dict] = None


class StepLog:
    """The per-step bookkeeping of an attack loop over B pairs (the weather attack's and the Lp
    attacks'): each pair's :class:`StepRecord` history and its best step so far, the one with
    the lowest distance to the target (the first measured step always counts), with its flow."""

    def __init__(self, size: int, on_step: Callable[[int, StepRecord], None]):
        self.history: list[list[StepRecord]] = [[] for _ in range(size)]
        self.best = [math.inf] * size
        self.best_step = [0] * size
        self.best_flow: list = [None] * size
        self.on_step = on_step

    def improves(self, i: int, step: int, distance: float, flow: torch.Tensor) -> bool:
        """Whether ``step`` is pair ``i``'s best so far; if so, keep its step, ``distance`` and
        flow (row ``i`` of ``flow``, detached, on the CPU)."""
        if distance < self.best[i] or self.best_flow[i] is None:
            self.best[i], self.best_step[i] = distance, step
            self.best_flow[i] = flow[i:i + 1].detach().cpu()
            return True
        return False

    def record(self, step: int, pairs: Sequence[int], flow: torch.Tensor, benign: torch.Tensor,
               losses: torch.Tensor, distances: Sequence[float], penalties: torch.Tensor,
               t0: float) -> None:
        """Append step ``step``'s :class:`StepRecord` to the history of each pair in ``pairs``
        and report it to ``on_step``; ``seconds`` is the time since ``t0``.
        Shape: flow and benign (B, 2, H, W), losses and penalties (B,), distances B floats."""
        robustness = aee(flow.detach(), benign).cpu().tolist()
        loss_values = losses.detach().cpu().tolist()
        penalty_values = penalties.detach().cpu().tolist()
        seconds = time.perf_counter() - t0
        for i in pairs:
            record = StepRecord(step=step, loss=loss_values[i], distance=distances[i],
                                penalty=penalty_values[i], robustness=robustness[i],
                                best_distance=self.best[i], seconds=seconds)
            self.history[i].append(record)
            self.on_step(i, record)
