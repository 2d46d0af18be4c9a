"""Make tests/models/reference_flows.npz: flows of the authors' GMA and FlowFormer code.

The authors' implementations are run with reproducible random weights (the same values our
networks get in tests/models/test_models_reference.py, from ``seeded_weights`` in
tests/models/model_layouts.py) on reproducible random frames; their flows are stored so that the tests
can check that our networks compute the same function, without the authors' code or weights.

Needs checkouts of https://github.com/zacjiang/GMA and
https://github.com/drinkingcoder/FlowFormer-Official and their Python dependencies (``einops``,
``scipy``; ``timm`` 0.4.12, ``yacs`` and ``loguru`` for FlowFormer). Nothing of theirs is part of
weathergen; this script only imports it from the given folders::

    python scripts/make_reference_flows.py --gma PATH/TO/GMA --flowformer PATH/TO/FlowFormer-Official
"""

from __future__ import annotations

import argparse
import importlib
import sys
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "models"))
from model_layouts import seeded_images, seeded_weights  # noqa: E402

#: Settings shared with tests/models/test_models_reference.py.
GMA_SEED, GMA_SIZE, GMA_ITERS = 1, (128, 144), 3
FF_SEED, FF_SIZE, FF_ITERS = 2, (64, 80), 3


def _coords_grid_float64(batch, ht, wd):
    # The authors' helper casts to float32; the float64 comparison needs it in float64.
    ys, xs = torch.meshgrid(torch.arange(ht), torch.arange(wd), indexing="ij")
    return torch.stack([xs, ys]).double()[None].repeat(batch, 1, 1, 1)


def gma_flow(repo: Path) -> np.ndarray:
    """The authors' RAFTGMA (content-only attention, one head) in float32, as released."""
    sys.path[:0] = [str(repo / "core")]
    from network import RAFTGMA

    args = Namespace(num_heads=1, position_only=False, position_and_content=False,
                     mixed_precision=False, dropout=0)
    model = RAFTGMA(args).eval()
    model.load_state_dict(seeded_weights(model.state_dict(), GMA_SEED))
    x1, x2 = seeded_images(GMA_SEED, *GMA_SIZE)
    with torch.no_grad():
        _, flow = model(255 * x1.float(), 255 * x2.float(), iters=GMA_ITERS, test_mode=True)
    for name in ("network", "utils", "utils.utils", "corr", "update", "extractor", "gma"):
        sys.modules.pop(name, None)
    sys.path.remove(str(repo / "core"))
    return flow[0].numpy()


def flowformer_flow(repo: Path) -> np.ndarray:
    """The authors' FlowFormer with the evaluation configuration, in float64."""
    sys.path[:0] = [str(repo), str(repo / "core")]
    torch.set_default_dtype(torch.float64)
    from configs.things_eval import get_cfg
    from core.FlowFormer import build_flowformer

    for name in ("utils.utils", "core.FlowFormer.LatentCostFormer.encoder",
                 "core.FlowFormer.LatentCostFormer.decoder",
                 "core.FlowFormer.LatentCostFormer.twins",
                 "core.FlowFormer.LatentCostFormer.transformer"):
        module = importlib.import_module(name)
        if hasattr(module, "coords_grid"):
            module.coords_grid = _coords_grid_float64
    cfg = get_cfg()
    cfg.latentcostformer.pretrain = False  # no ImageNet download: the weights are replaced
    cfg.latentcostformer.decoder_depth = FF_ITERS
    model = build_flowformer(cfg).eval()
    model.load_state_dict(seeded_weights(model.state_dict(), FF_SEED))
    x1, x2 = seeded_images(FF_SEED, *FF_SIZE)
    with torch.no_grad():
        flow, _ = model(255 * x1, 255 * x2)
    torch.set_default_dtype(torch.float32)
    return flow[0].numpy()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gma", type=Path, required=True, help="checkout of zacjiang/GMA")
    parser.add_argument("--flowformer", type=Path, required=True,
                        help="checkout of drinkingcoder/FlowFormer-Official")
    parser.add_argument("--out", type=Path,
                        default=ROOT / "tests" / "models" / "reference_flows.npz")
    args = parser.parse_args()
    gma = gma_flow(args.gma)
    flowformer = flowformer_flow(args.flowformer)
    np.savez_compressed(args.out, gma=gma.astype(np.float32), flowformer=flowformer)
    print(f"wrote {args.out}: gma {gma.shape} (max |flow| {np.abs(gma).max():.3f}), "
          f"flowformer {flowformer.shape} (max |flow| {np.abs(flowformer).max():.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
