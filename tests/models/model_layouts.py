"""Parameter names and shapes of the flow networks' released checkpoints, written from the
published architectures (not from our modules), for the layout tests."""

from __future__ import annotations


def raft_encoder_layout(prefix: str, out_dim: int, norm: str) -> dict:
    """Keys and shapes of RAFT's BasicEncoder as the released RAFT/GMA files hold them: a 7x7
    stem of 64 channels, three stages of two residual blocks (64, 96, 128 channels; the first
    block of stages 2 and 3 has stride 2 and a 1x1 shortcut whose normalisation is saved twice,
    as norm3 and as downsample.1), and a 1x1 head."""
    out = {}

    def conv(name, o, i, k):
        out[f"{prefix}{name}.weight"] = (o, i, k, k)
        out[f"{prefix}{name}.bias"] = (o,)

    def normalisation(name, c):
        if norm == "batch":
            for p in ("weight", "bias", "running_mean", "running_var"):
                out[f"{prefix}{name}.{p}"] = (c,)
            out[f"{prefix}{name}.num_batches_tracked"] = ()

    conv("conv1", 64, 3, 7)
    normalisation("norm1", 64)
    chans = 64
    for layer, width in ((1, 64), (2, 96), (3, 128)):
        for block in (0, 1):
            name = f"layer{layer}.{block}"
            conv(f"{name}.conv1", width, chans, 3)
            conv(f"{name}.conv2", width, width, 3)
            normalisation(f"{name}.norm1", width)
            normalisation(f"{name}.norm2", width)
            if block == 0 and layer > 1:
                normalisation(f"{name}.norm3", width)
                conv(f"{name}.downsample.0", width, chans, 1)
                normalisation(f"{name}.downsample.1", width)
            chans = width
    conv("conv2", out_dim, 128, 1)
    return out


def gma_update_layout(prefix: str, corr_channels: int) -> dict:
    """GMA's update block: RAFT's motion encoder, a separable GRU reading 128 context + 128 motion
    + 128 aggregated channels, flow head, upsampling mask, aggregator (to_v, gamma)."""
    shapes = {
        "encoder.convc1": (256, corr_channels, 1, 1), "encoder.convc2": (192, 256, 3, 3),
        "encoder.convf1": (128, 2, 7, 7), "encoder.convf2": (64, 128, 3, 3),
        "encoder.conv": (126, 256, 3, 3),
        "flow_head.conv1": (256, 128, 3, 3), "flow_head.conv2": (2, 256, 3, 3),
        "mask.0": (256, 128, 3, 3), "mask.2": (576, 256, 1, 1),
    }
    for gate in "zrq":
        shapes[f"gru.conv{gate}1"] = (128, 512, 1, 5)
        shapes[f"gru.conv{gate}2"] = (128, 512, 5, 1)
    out = {}
    for name, shape in shapes.items():
        out[f"{prefix}{name}.weight"] = shape
        out[f"{prefix}{name}.bias"] = (shape[0],)
    out[f"{prefix}aggregator.to_v.weight"] = (128, 128, 1, 1)
    out[f"{prefix}aggregator.gamma"] = (1,)
    return out


def gma_attention_layout(prefix: str) -> dict:
    return {f"{prefix}to_qk.weight": (256, 128, 1, 1),
            f"{prefix}pos_emb.rel_height.weight": (319, 128),
            f"{prefix}pos_emb.rel_width.weight": (319, 128),
            f"{prefix}pos_emb.rel_ind": (160, 160)}


def seeded_weights(state: dict, seed: int) -> dict:
    """Reproducible random weights for a state dict, the same for every implementation that has
    the same key names and shapes (used to compare with the authors' code, see
    scripts/make_reference_flows.py): keys in sorted order, float64 draws from one generator;
    normalisation scales near 1, running variances in [0.5, 1.5], everything else N(0, 0.05^2),
    GMA's aggregation weight gamma 0.5."""
    import torch

    g = torch.Generator().manual_seed(seed)
    out = {}
    for key in sorted(state):
        value = state[key]
        if not value.is_floating_point():
            out[key] = value.clone()
            continue
        noise = torch.randn(value.shape, generator=g, dtype=torch.float64)
        if key.endswith("running_var"):
            new = 1.0 + 0.5 * torch.tanh(noise)
        elif key.endswith("running_mean"):
            new = 0.05 * noise
        elif key.endswith("aggregator.gamma"):
            new = torch.full(value.shape, 0.5, dtype=torch.float64)
        elif key.endswith(".weight") and value.dim() == 1:
            new = 1.0 + 0.05 * noise
        else:
            new = 0.05 * noise
        out[key] = new.to(value.dtype)
    return out


def seeded_images(seed: int, height: int, width: int):
    """Two reproducible ``(1, 3, H, W)`` float64 frames in [0, 1]."""
    import torch

    g = torch.Generator().manual_seed(seed)
    return (torch.rand(1, 3, height, width, generator=g, dtype=torch.float64),
            torch.rand(1, 3, height, width, generator=g, dtype=torch.float64))


def spynet_weights(state: dict, seed: int, gain: float = 0.1) -> dict:
    """:func:`seeded_weights` for a SpyNet state dict, with each level's last convolution
    scaled by ``gain``: the flow stays within a few pixels (unscaled, random levels add up to
    hundreds of pixels, and every sample would fall outside the frame)."""
    out = seeded_weights(state, seed)
    return {k: v * gain if ".moduleBasic.8." in k else v for k, v in out.items()}
