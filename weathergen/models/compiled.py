"""``torch.compile`` for the part of a recurrent network that every refinement iteration runs.

RAFT, RAFT-small and GMA repeat their update block (a convolutional GRU and the motion encoder)
``iters`` times on tensors of one shape; FlowFormer repeats its flow-token encoder, the cost-query
attention of its decoder layer and a GMA update block. :func:`compile_iterations` compiles those
modules in place (``nn.Module.compile``: the state dict keeps its keys), so a compiled graph is
traced once and replayed at every iteration and every attack step. The encoders, which run once
per pair, stay eager. Networks without iterations (SpyNet, the FlowNets) have nothing to compile.

What changes: the order of floating-point operations inside the fused kernels (Inductor), so a
compiled network's flow equals the eager one's within float32 rounding (tested on the CPU;
``docs/scale.md`` gives the measured differences); the first call of each input shape pays the
compilation (tens of seconds). On CUDA, ``mode="reduce-overhead"`` also replays the kernels as
CUDA graphs.
"""

from __future__ import annotations

from torch import nn

from ..errors import ConfigError

#: The modes offered (those of ``torch.compile``).
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune-no-cudagraphs")
#: Names of the submodules that a refinement iteration runs.
ITERATION_MODULES = ("update_block", "flow_token_encoder", "decoder_layer")


def iteration_modules(model: nn.Module) -> list[tuple[str, nn.Module]]:
    """The submodules of ``model`` that every refinement iteration runs, with their names."""
    return [(name, module) for name, module in model.named_modules()
            if name.rsplit(".", 1)[-1] in ITERATION_MODULES]


def compile_iterations(model: nn.Module, mode: str = "default", backend: str = "inductor"
                       ) -> list[str]:
    """Compile the iteration modules of ``model`` in place with ``torch.compile(mode=mode)``
    (``backend``: torch.compile's; ``"aot_eager"`` traces without generating kernels, which tests
    use to check the wiring quickly).

    Returns the names of the modules compiled (empty for a network without iterations).
    Raises ConfigError for an unknown ``mode``.
    """
    if mode not in COMPILE_MODES:
        raise ConfigError(f"compile mode {mode!r}: expected one of {', '.join(COMPILE_MODES)}")
    found = iteration_modules(model)
    for _, module in found:
        module.compile(mode=None if backend != "inductor" else mode, backend=backend,
                       dynamic=False)
    return [name for name, _ in found]
