"""A batched attack step on CUDA moves the particles as on the CPU (run by `make gpu-check`).

RAFT-small with random weights, two synthetic pairs, TF32 off; skipped without a CUDA device.
"""

from __future__ import annotations

import pytest
import torch

from engine_scenes import plane_pair
from weathergen.attack import AttackSettings, BatchOptimisation
from weathergen.engine import load_preset, sample_particles
from weathergen.models import build_model

pytestmark = pytest.mark.cuda


def test_a_batch_attack_step_on_cuda_matches_the_cpu():
    before = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        torch.manual_seed(0)
        model = build_model("raft-small", iters=3)
        pairs = [plane_pair(64, 96, depth=2.5, near_block=True, seed=s) for s in (0, 1)]
        records = [sample_particles(p, load_preset("snow", {"count": 100}), seed=s)
                   for s, p in enumerate(pairs)]
        losses = {}
        for device in ("cpu", "cuda"):
            run = BatchOptimisation(model.to(device), pairs, records,
                                    AttackSettings(steps=1, lr=1e-3), device=device)
            first = run.evaluate()[2]
            run.update(first.sum())
            # (Adam's first step is lr times the gradient's sign: compare what it leads to)
            losses[device] = (first.detach().cpu(), run.evaluate()[2].detach().cpu())
        for before_step, after_step in zip(losses["cuda"], losses["cpu"]):
            torch.testing.assert_close(before_step, after_step, rtol=1e-2, atol=1e-4)
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = before
