"""Optical-flow networks behind one contract, looked up by name.

    >>> from weathergen.models import get_model
    >>> model = get_model("raft-small", iters=12)       # doctest: +SKIP
    >>> flow = model(image1, image2)                    # doctest: +SKIP

Shape: images ``(B, 3, H, W)`` RGB in ``[0, 1]`` of any size -> flow ``(B, 2, H, W)`` in pixels.
Each network is one module of this package that registers itself on import (see
:mod:`weathergen.models.registry`); importing this package imports them all. Networks from
outside the package (``FILE.py:NAME``, ``package.module:NAME``, entry points of the group
``weathergen.models``) are loaded by :mod:`weathergen.models.external` when named.
"""

from .base import AUTOCAST, PRECISIONS, FlowModel
from .compiled import COMPILE_MODES, compile_iterations
from .checkpoints import CheckpointSpec, cache_dir, download_checkpoint, read_state_dict
from .padding import InputPadder
from .external import (ENTRY_POINT_GROUP, INPUT_CONVENTIONS, ModuleFlowModel, entry_points,
                       flow_input, probe_network)
from .registry import (ModelSpec, Network, available_checkpoints, available_models, build_model,
                       checkpoint_spec, get_model, model_spec, register_checkpoint, register_model,
                       resolve_amp, resolve_network, resolve_precision)

# Network modules register themselves; import each one here.
from . import raft  # noqa: E402,F401  (registration side effect)
from . import gma  # noqa: E402,F401
from . import flowformer  # noqa: E402,F401
from .raft import RAFT, RAFTModel  # noqa: E402
from . import spynet, flownetc, flownetcrobust, flownet2  # noqa: E402,F401
from .spynet import SpyNet, SpyNetModel, SpyNetSniklaus, SpyNetSniklausModel  # noqa: E402
from .flownetc import FlowNetC, FlowNetCModel  # noqa: E402
from .flownetcrobust import FlowNetCRobust, FlowNetCRobustModel  # noqa: E402
from .flownet2 import FlowNet2, FlowNet2Model  # noqa: E402
from .gma import GMA, GMAModel  # noqa: E402
from .flowformer import FlowFormer, FlowFormerModel  # noqa: E402

__all__ = [
    "FlowModel", "InputPadder", "ModelSpec", "CheckpointSpec", "RAFT", "RAFTModel", "GMA",
    "GMAModel", "FlowFormer", "FlowFormerModel",
    "get_model", "build_model", "available_models", "available_checkpoints", "model_spec",
    "checkpoint_spec", "register_model", "register_checkpoint", "resolve_amp", "resolve_precision", "cache_dir",
    "download_checkpoint", "read_state_dict", "ENTRY_POINT_GROUP", "ModuleFlowModel",
    "Network", "resolve_network", "flow_input", "probe_network", "INPUT_CONVENTIONS",
    "entry_points", "COMPILE_MODES", "compile_iterations",
    "SpyNet", "SpyNetModel", "SpyNetSniklaus", "SpyNetSniklausModel", "FlowNetC", "FlowNetCModel", "FlowNetCRobust",
    "FlowNetCRobustModel", "FlowNet2", "FlowNet2Model", "PRECISIONS", "AUTOCAST",
]
