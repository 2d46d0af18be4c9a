"""Make tests/models/reference_flows.npz: flows of the reference implementations.

The reference implementations are run with reproducible random weights (the same values our
networks get in tests/models/test_models_reference.py, from ``seeded_weights`` and
``spynet_weights`` in tests/models/model_layouts.py) on reproducible random frames; their flows
are stored so that the tests can check that our networks compute the same function, without the
reference code or weights:

- ``gma``: the authors' GMA (https://github.com/zacjiang/GMA; needs ``einops``, ``scipy``);
- ``flowformer``: the authors' FlowFormer (https://github.com/drinkingcoder/FlowFormer-Official;
  ``timm`` 0.4.12, ``yacs``, ``loguru``);
- ``spynet``: the SpyNet of the paper's research code
  (https://github.com/cv-stuttgart/DistractingDownpour, ``models/SpyNet/SpyNet.py``: the SpyNet
  authors' PyTorch module), with the research code's padding to a multiple of 64;
- ``spynet_sniklaus``: ``Network`` of https://github.com/sniklaus/pytorch-spynet (``run.py``),
  fed BGR frames as its ``estimate`` feeds them, at a size its resizing leaves unchanged.

Nothing of theirs is part of weathergen; this script only imports it from the given folders.
Give any of the options; the flows of the others are kept from the existing file::

    python scripts/make_reference_flows.py --gma PATH/TO/GMA --flowformer PATH/TO/FlowFormer-Official \
        --spynet PATH/TO/DistractingDownpour --spynet-sniklaus PATH/TO/pytorch-spynet
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys
import types
import warnings
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "models"))
from model_layouts import seeded_images, seeded_weights, spynet_weights  # noqa: E402

from weathergen.models import build_model  # noqa: E402

#: Settings shared with tests/models/test_models_reference.py.
GMA_SEED, GMA_SIZE, GMA_ITERS = 1, (128, 144), 3
FF_SEED, FF_SIZE, FF_ITERS = 2, (64, 80), 3
SPYNET_SEED, SPYNET_SIZE = 3, (72, 100)
SNIKLAUS_SEED, SNIKLAUS_SIZE = 4, (64, 96)


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


def _load_file(name: str, path: Path):
    """Import one file of a reference code base as module ``name``."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _stub_modules(*names: str) -> None:
    """Empty modules for imports the reference files make but the flow does not use (PIL)."""
    for name in names:
        sys.modules.setdefault(name, types.ModuleType(name))


def spynet_flow(repo: Path) -> np.ndarray:
    """The research code's SpyNet (six levels) in float64, padded as the research code pads."""
    _stub_modules("PIL", "PIL.Image")
    config = types.ModuleType("helper_functions.config_specs")

    class Conf:                  # the research code's settings: run on the CPU
        @staticmethod
        def config(key):
            return key == "useCPU"

    config.Conf = Conf
    sys.modules["helper_functions"] = types.ModuleType("helper_functions")
    sys.modules["helper_functions.config_specs"] = config
    torch.set_default_dtype(torch.float64)
    module = _load_file("research_spynet", repo / "models" / "SpyNet" / "SpyNet.py")
    real_load = torch.load
    torch.load = lambda *args, **kwargs: torch.zeros(())  # its released files: replaced below
    try:
        model = module.Network(nlevels=6, pretrained=True).eval()
    finally:
        torch.load = real_load
    model.load_state_dict(spynet_weights(model.state_dict(), SPYNET_SEED))
    x1, x2 = seeded_images(SPYNET_SEED, *SPYNET_SIZE)
    # The research code's InputPadder(divisor=64), "sintel" mode: replicated borders, split evenly.
    ht, wd = SPYNET_SIZE
    pad_ht, pad_wd = (-ht) % 64, (-wd) % 64
    pad = [pad_wd // 2, pad_wd - pad_wd // 2, pad_ht // 2, pad_ht - pad_ht // 2]
    x1, x2 = (torch.nn.functional.pad(x, pad, mode="replicate") for x in (x1, x2))
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")   # its deprecated upsample and grid_sample defaults
        flow = model(x1, x2)
    torch.set_default_dtype(torch.float32)
    return flow[0, :, pad[2]:pad[2] + ht, pad[0]:pad[0] + wd].numpy()


def spynet_sniklaus_flow(repo: Path) -> np.ndarray:
    """The port's ``Network`` in float64 on a size that its ``estimate`` does not resize."""
    _stub_modules("PIL", "PIL.Image")
    argv, sys.argv = sys.argv, ["run.py"]      # run.py parses the command line on import
    torch.set_default_dtype(torch.float64)
    try:
        module = _load_file("sniklaus_spynet", repo / "run.py")
    finally:
        sys.argv = argv
    torch.set_grad_enabled(True)                # run.py turns gradients off globally
    # The port's released key names (which its Network renames on loading) and shapes.
    state = spynet_weights(build_model("spynet-sniklaus").network.state_dict(), SNIKLAUS_SEED)
    real_hub, real_cuda = torch.hub.load_state_dict_from_url, torch.Tensor.cuda
    torch.hub.load_state_dict_from_url = lambda **kwargs: state   # instead of the download
    torch.Tensor.cuda = lambda self, *args, **kwargs: self         # its grid goes to CUDA
    try:
        model = module.Network().eval()
        x1, x2 = seeded_images(SNIKLAUS_SEED, *SNIKLAUS_SIZE)
        with torch.no_grad():
            flow = model(x1.flip(1), x2.flip(1))    # BGR, as estimate() passes the frames
    finally:
        torch.hub.load_state_dict_from_url, torch.Tensor.cuda = real_hub, real_cuda
    torch.set_default_dtype(torch.float32)
    return flow[0].numpy()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gma", type=Path, help="checkout of zacjiang/GMA")
    parser.add_argument("--flowformer", type=Path,
                        help="checkout of drinkingcoder/FlowFormer-Official")
    parser.add_argument("--spynet", type=Path, help="checkout of cv-stuttgart/DistractingDownpour")
    parser.add_argument("--spynet-sniklaus", type=Path, help="checkout of sniklaus/pytorch-spynet")
    parser.add_argument("--out", type=Path,
                        default=ROOT / "tests" / "models" / "reference_flows.npz")
    args = parser.parse_args()
    flows = dict(np.load(args.out)) if args.out.is_file() else {}
    if args.gma:
        flows["gma"] = gma_flow(args.gma).astype(np.float32)
    if args.flowformer:
        flows["flowformer"] = flowformer_flow(args.flowformer)
    if args.spynet:
        flows["spynet"] = spynet_flow(args.spynet)
    if args.spynet_sniklaus:
        flows["spynet_sniklaus"] = spynet_sniklaus_flow(args.spynet_sniklaus)
    np.savez_compressed(args.out, **flows)
    print(f"wrote {args.out}: " + ", ".join(
        f"{name} {flow.shape} {flow.dtype} (max |flow| {np.abs(flow).max():.3f})"
        for name, flow in flows.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
