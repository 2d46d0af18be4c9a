"""SpyNet (Ranjan and Black, "Optical Flow Estimation using a Spatial Pyramid Network",
CVPR 2017), in the two PyTorch forms in use.

A coarse-to-fine pyramid with one small CNN per level: both frames are averaged 2x2 down to the
coarsest level; from there on, the flow of the coarser level is upsampled (values doubled),
frame 2 is warped towards frame 1 with it, and the level's network (five 7x7 convolutions:
8 -> 32 -> 64 -> 32 -> 16 -> 2 channels, ReLU between) adds a residual flow predicted from
frame 1, the warped frame 2 and the upsampled flow (3 + 3 + 2 channels). The coarsest level
starts from zero flow; the finest level's output is the flow in pixels.

The two forms differ in the pyramid, the upsampling and the warping:

=====================  ===========================================  ==============================
                       ``spynet`` (:class:`SpyNet`)                 ``spynet-sniklaus``
=====================  ===========================================  ==============================
where from             the SpyNet authors' PyTorch code, which the  Simon Niklaus's port
                       paper's research code runs                   (github.com/sniklaus/
                                                                    pytorch-spynet)
levels                 always six (five halvings)                   up to six, while a level is
                                                                    larger than 32 pixels
input size             padded to a multiple of 64                   a multiple of 32 (the port
                                                                    resizes; we pad)
upsampling             bilinear, half-pixel centres                 bilinear, corner-aligned
warping                see :func:`clamped_grid_warp`                bilinear, border clamped
=====================  ===========================================  ==============================

Both read the weights of the authors' release: six Torch7 files per model, ``modelL1_F.t7`` ...
``modelL6_F.t7`` (``F`` Sintel final, ``C`` Sintel clean, ``K`` KITTI, ``3`` / ``4`` Chairs final /
clean, which have five levels: the sixth runs the fifth's weights, as the authors' code does).
Parameter names: ``moduleBasic.<level>.moduleBasic.<0,2,4,6,8>.weight|bias``, level 0 coarsest,
as in the authors' PyTorch module and in the port's released files.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Optional, Sequence

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint as recompute

from ..errors import FormatError, ShapeError
from ..io.torch7 import Torch7Object, read_torch7
from .base import FlowModel, in_float32
from .checkpoints import (CheckpointSpec, load_strict, read_state_dict, read_tensor_file,
                          strip_prefix)
from .flownet_parts import warp as border_warp
from .registry import ModelSpec, register_checkpoint, register_model

#: ImageNet statistics the released models normalise RGB in [0, 1] with.
RGB_MEAN = (0.485, 0.456, 0.406)
RGB_STD = (0.229, 0.224, 0.225)

#: Pyramid levels of the released models.
LEVELS = 6
#: (out, in) channels of the five 7x7 convolutions of one level.
LEVEL_CONVOLUTIONS = ((32, 8), (64, 32), (32, 64), (16, 32), (2, 16))
KERNEL = 7

#: The released models: name -> the letter of their files (``modelL<n>_<letter>.t7``).
VARIANTS = {"sintel-final": "F", "sintel-clean": "C", "kitti-final": "K", "chairs-final": "3",
            "chairs-clean": "4"}
#: Models released with five levels; their sixth level runs the fifth's weights.
FIVE_LEVEL_LETTERS = ("3", "4")


# -- the networks -------------------------------------------------------------------------------

class SpyNetLevel(nn.Module):
    """The network of one pyramid level.

    Shape: ``(B, 8, h, w)`` (frame 1, warped frame 2, upsampled flow) -> ``(B, 2, h, w)``.
    """

    def __init__(self):
        super().__init__()
        layers: list[nn.Module] = []
        for i, (cout, cin) in enumerate(LEVEL_CONVOLUTIONS):
            if i:
                layers.append(nn.ReLU())
            layers.append(nn.Conv2d(cin, cout, KERNEL, padding=KERNEL // 2))
        self.moduleBasic = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.moduleBasic(x)


class _Pyramid(nn.Module):
    """What both forms share: the level networks and the coarse-to-fine loop. Subclasses say how
    many halvings a size gets, how a flow is upsampled and how frame 2 is warped."""

    def __init__(self, levels: int = LEVELS):
        super().__init__()
        self.moduleBasic = nn.ModuleList([SpyNetLevel() for _ in range(levels)])

    def halvings(self, height: int, width: int) -> int:
        raise NotImplementedError

    def upsample(self, flow: torch.Tensor) -> torch.Tensor:
        """The flow of the coarser level at twice its size, in pixels of the finer level."""
        raise NotImplementedError

    def warp(self, image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def forward(self, image1: torch.Tensor, image2: torch.Tensor,
                gradient_checkpointing: bool = False) -> torch.Tensor:
        """Flow of normalised frames ``(B, 3, H, W)`` -> ``(B, 2, H, W)`` pixels.

        ``gradient_checkpointing``: recompute each level in the backward pass.
        """
        pyramid = [(image1, image2)]
        for _ in range(self.halvings(image1.shape[-2], image1.shape[-1])):
            first, second = pyramid[0]
            pyramid.insert(0, (F.avg_pool2d(first, 2), F.avg_pool2d(second, 2)))
        top = pyramid[0][0]
        flow = top.new_zeros(top.shape[0], 2, top.shape[-2] // 2, top.shape[-1] // 2)
        use_recompute = gradient_checkpointing and torch.is_grad_enabled()
        for level, (first, second) in enumerate(pyramid):
            if use_recompute:
                flow = recompute(self._refine, level, first, second, flow, use_reentrant=False)
            else:
                flow = self._refine(level, first, second, flow)
        return flow

    def _refine(self, level: int, first: torch.Tensor, second: torch.Tensor,
                coarse_flow: torch.Tensor) -> torch.Tensor:
        """One pyramid level: upsample the coarser flow, warp, predict the residual."""
        up = self.upsample(coarse_flow)
        # An odd level size: the doubled coarse flow is one short; repeat its last row / column.
        if up.shape[-2] != first.shape[-2]:
            up = F.pad(up, (0, 0, 0, first.shape[-2] - up.shape[-2]), mode="replicate")
        if up.shape[-1] != first.shape[-1]:
            up = F.pad(up, (0, first.shape[-1] - up.shape[-1], 0, 0), mode="replicate")
        step = self.moduleBasic[level]
        return step(torch.cat([first, self.warp(second, up), up], dim=1)) + up


@in_float32
def clamped_grid_warp(image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Frame 2 warped as the SpyNet authors' PyTorch code warps it (under PyTorch >= 1.3).

    Their code builds a corner-aligned sampling grid (``x + u`` over ``(W - 1) / 2``, minus 1),
    clamps it to [-1, 1] and hands it to ``grid_sample`` with that function's default since
    PyTorch 1.3, half-pixel centres, and zeros outside. In pixels: the point ``s = x + u`` is
    clamped into ``[0, W - 1]`` and then sampled at ``s * W / (W - 1) - 1/2``, a grid stretched
    by ``W / (W - 1)`` and shifted by half a pixel; at the clamped extremes (``-1/2`` and
    ``W - 1/2``) half of the sample is the zero outside the image. The same holds for ``y``.

    Shape: ``image`` ``(B, C, H, W)``, ``flow`` ``(B, 2, H, W)`` in pixels, ``H, W >= 2`` ->
    ``(B, C, H, W)``. Its gradient in the flow is zero where the clamp holds.
    """
    b, _, h, w = flow.shape
    ys = torch.arange(h, dtype=flow.dtype, device=flow.device).view(1, h, 1)
    xs = torch.arange(w, dtype=flow.dtype, device=flow.device).view(1, 1, w)
    x = (xs + flow[:, 0]).clamp(0, w - 1) * (w / (w - 1)) - 0.5
    y = (ys + flow[:, 1]).clamp(0, h - 1) * (h / (h - 1)) - 0.5
    # grid_sample's corner-aligned normalisation: -1 and 1 are the border pixels' centres.
    grid = torch.stack([2.0 * x / (w - 1) - 1.0, 2.0 * y / (h - 1) - 1.0], dim=-1)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=True)


class SpyNet(_Pyramid):
    """SpyNet as the SpyNet authors' PyTorch code computes it, the network the paper attacked.

    Always six levels (five halvings), half-pixel bilinear upsampling of the coarser flow, and
    :func:`clamped_grid_warp`. Height and width must be multiples of 32 and at least 64 (the
    coarsest level is then at least 2 x 2); the adapter pads to a multiple of 64, as the
    research code does.

    Shape: ``image1``, ``image2`` ``(B, 3, H, W)`` normalised -> ``(B, 2, H, W)`` flow in pixels.
    """

    def halvings(self, height: int, width: int) -> int:
        n = len(self.moduleBasic) - 1
        if min(height, width) < 2 << n or height % (1 << n) or width % (1 << n):
            raise ShapeError(f"expected SpyNet frames whose height and width are multiples of "
                             f"{1 << n} and at least {2 << n}, got {height} x {width}")
        return n

    def upsample(self, flow: torch.Tensor) -> torch.Tensor:
        return 2.0 * F.interpolate(flow, scale_factor=2, mode="bilinear", align_corners=False)

    def warp(self, image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
        return clamped_grid_warp(image, flow)


class SpyNetSniklaus(_Pyramid):
    """SpyNet as Simon Niklaus's PyTorch port computes it.

    The pyramid has one level more for each halving while the current level is larger than
    32 pixels in height or width (at most five halvings); the networks of the coarsest levels
    are used, from level 0 on, so small frames use fewer of them. Corner-aligned bilinear
    upsampling; warping bilinear with positions outside clamped to the border.

    Shape: ``image1``, ``image2`` ``(B, 3, H, W)`` normalised -> ``(B, 2, H, W)`` flow in pixels.
    """

    def halvings(self, height: int, width: int) -> int:
        n = 0
        while n < len(self.moduleBasic) - 1 and (height > 32 or width > 32):
            height, width = height // 2, width // 2
            n += 1
        return n

    def upsample(self, flow: torch.Tensor) -> torch.Tensor:
        return 2.0 * F.interpolate(flow, scale_factor=2, mode="bilinear", align_corners=True)

    def warp(self, image: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
        return border_warp(image, flow)


# -- the adapters -------------------------------------------------------------------------------

class _SpyNetAdapter(FlowModel):
    """RGB in ``[0, 1]`` minus the ImageNet mean, over the ImageNet standard deviation (per
    channel); padding with replicated borders; ``iters`` ignored (not recurrent)."""

    network_class: type = _Pyramid

    def __init__(self, iters: Optional[int] = None, gradient_checkpointing: bool = False):
        super().__init__()
        self.network = self.network_class()
        self.gradient_checkpointing = gradient_checkpointing

    def normalize(self, image: torch.Tensor) -> torch.Tensor:
        # The constants in the image's precision (float32 copies would round them in float64).
        mean = torch.tensor(RGB_MEAN, dtype=image.dtype, device=image.device).view(1, 3, 1, 1)
        std = torch.tensor(RGB_STD, dtype=image.dtype, device=image.device).view(1, 3, 1, 1)
        return (image - mean) / std

    def predict(self, image1: torch.Tensor, image2: torch.Tensor) -> torch.Tensor:
        return self.network(image1, image2, gradient_checkpointing=self.gradient_checkpointing)


class SpyNetModel(_SpyNetAdapter):
    """The paper's SpyNet (:class:`SpyNet`) behind the package contract.

    Padding: to a multiple of 64, as the research code pads. Checkpoints: a file holding the
    state dict (``moduleBasic.*``, with or without ``module.``), or the authors' per-level files
    (see :func:`read_level_files`): one of them or their folder.
    """

    architecture = "spynet"
    network_class = SpyNet
    multiple = 64
    min_size = 64

    def read_checkpoint(self, path) -> dict:
        path = Path(path)
        if path.is_dir() or level_file_kind(path.name) is not None:
            return read_level_files(path)
        return read_state_dict(path)

    def load_checkpoint(self, state_dict: dict, source, what: str) -> None:
        load_strict(self.network, strip_prefix(state_dict, "module."), source, what)


class SpyNetSniklausModel(_SpyNetAdapter):
    """The port's SpyNet (:class:`SpyNetSniklaus`) behind the package contract.

    Padding: to a multiple of 32 (the port resizes instead, which rescales the flow). Its
    files: ``moduleBasic.*`` (the released ``network-<variant>.pytorch``) or ``netBasic.*``
    (saved by the port's current code), with or without ``module.``.
    """

    architecture = "spynet-sniklaus"
    network_class = SpyNetSniklaus
    multiple = 32
    min_size = 32

    def load_checkpoint(self, state_dict: dict, source, what: str) -> None:
        state_dict = strip_prefix(state_dict, "module.")
        if state_dict and all(k.startswith("netBasic.") for k in state_dict):
            state_dict = {k.replace("netBasic", "moduleBasic"): v for k, v in state_dict.items()}
        load_strict(self.network, state_dict, source, what)


# -- the authors' per-level files ---------------------------------------------------------------

#: ``modelL<level>_<letter>.t7``: one level, as the SpyNet authors publish it (Torch7).
_TORCH7_FILE = re.compile(r"^modelL([1-9])_([0-9A-Za-z]+)\.t7$")
#: ``modelL<level>_<letter>-<conv>-<weight|bias>.pth.tar``: one tensor each, as converted to
#: PyTorch in the authors' adversarial-patch code (github.com/anuragranj/flowattack), the files
#: the paper's research code loads.
_TENSOR_FILE = re.compile(r"^modelL([1-9])_([0-9A-Za-z]+)-([1-9])-(weight|bias)\.pth\.tar$")


def level_file_kind(name: str) -> Optional[str]:
    """``"torch7"`` or ``"tensor"`` for the name of one of the authors' per-level files,
    else ``None``."""
    if _TORCH7_FILE.match(name):
        return "torch7"
    if _TENSOR_FILE.match(name):
        return "tensor"
    return None


def level_file_names(letter: str, kind: str = "torch7") -> list[str]:
    """The files of one released model, level 1 (coarsest) first; for the five-level models the
    fifth level's files stand in for the sixth."""
    names = []
    for level in range(1, LEVELS + 1):
        source = LEVELS - 1 if level == LEVELS and letter in FIVE_LEVEL_LETTERS else level
        if kind == "torch7":
            names.append(f"modelL{source}_{letter}.t7")
        else:
            names += [f"modelL{source}_{letter}-{conv}-{part}.pth.tar"
                      for conv in range(1, len(LEVEL_CONVOLUTIONS) + 1)
                      for part in ("weight", "bias")]
    return names


def read_level_files(path: str | Path) -> dict[str, torch.Tensor]:
    """The state dict of one released SpyNet model from the authors' per-level files.

    ``path`` is one of the files (``modelL1_F.t7``, ``modelL3_F-2-bias.pth.tar``), which selects
    its model (the letter) and its folder, or a folder that holds the files of exactly one
    model. Torch7 files (six per model) are read with :func:`~weathergen.io.torch7.read_torch7`:
    each holds the level's ``nn.Sequential`` whose five spatial convolutions are taken in order;
    the converted PyTorch files hold one tensor each (60 per model).

    Raises:
        FormatError: naming the file (or folder) that is missing, unreadable or of the wrong
            content (number or shapes of the convolutions).
    """
    path = Path(path)
    folder, kind, letter = _level_files_of(path)
    state = {}
    if kind == "torch7":
        for level, name in enumerate(level_file_names(letter, "torch7")):
            for conv, (weight, bias) in enumerate(_torch7_convolutions(folder / name)):
                state[_key(level, conv, "weight")] = weight
                state[_key(level, conv, "bias")] = bias
        return state
    names = iter(level_file_names(letter, "tensor"))
    for level in range(LEVELS):
        for conv, (cout, cin) in enumerate(LEVEL_CONVOLUTIONS):
            for part, shape in (("weight", (cout, cin, KERNEL, KERNEL)), ("bias", (cout,))):
                file = folder / next(names)
                if not file.is_file():
                    raise FormatError(file, f"missing: SpyNet model {letter!r} needs "
                                            f"{len(level_file_names(letter, 'tensor'))} such "
                                            f"files in {folder}")
                tensor = read_tensor_file(file)
                if tuple(tensor.shape) != shape:
                    raise FormatError(file, f"holds a tensor of shape {tuple(tensor.shape)}, "
                                            f"expected {shape}")
                state[_key(level, conv, part)] = tensor.float()
    return state


def pack_level_files(paths: Sequence[Path]) -> dict[str, torch.Tensor]:
    """The state dict of the per-level files ``paths`` (all in one folder); the packing step of
    a download."""
    return read_level_files(paths[0])


def _key(level: int, conv: int, part: str) -> str:
    return f"moduleBasic.{level}.moduleBasic.{2 * conv}.{part}"


def _level_files_of(path: Path) -> tuple[Path, str, str]:
    """(folder, kind, letter) of a per-level file or a folder of them."""
    if not path.is_dir():
        match = _TORCH7_FILE.match(path.name) or _TENSOR_FILE.match(path.name)
        if match is None:
            raise FormatError(path, "is not one of SpyNet's per-level files (modelL<n>_<model>.t7 "
                                    "or modelL<n>_<model>-<k>-weight|bias.pth.tar)")
        return path.parent, level_file_kind(path.name), match.group(2)
    found = set()
    for child in path.iterdir():
        kind = level_file_kind(child.name)
        if kind is not None:
            match = (_TORCH7_FILE if kind == "torch7" else _TENSOR_FILE).match(child.name)
            found.add((kind, match.group(2)))
    if len(found) != 1:
        held = ", ".join(f"{letter} ({kind})" for kind, letter in sorted(found)) or "none"
        raise FormatError(path, f"expected the per-level files of exactly one SpyNet model in "
                                f"this folder, found models: {held}; give one file instead, e.g. "
                                f"{path / 'modelL1_F.t7'}")
    kind, letter = found.pop()
    return path, kind, letter


def _torch7_convolutions(path: Path) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The five (weight, bias) pairs of one level's Torch7 file, checked against the shapes."""
    if not path.is_file():
        raise FormatError(path, "missing: the SpyNet model needs this per-level file")
    convs: list[Torch7Object] = []
    _collect_convolutions(read_torch7(path), convs)
    if len(convs) != len(LEVEL_CONVOLUTIONS):
        raise FormatError(path, f"holds {len(convs)} spatial convolutions, expected "
                                f"{len(LEVEL_CONVOLUTIONS)} (one SpyNet level)")
    out = []
    for i, (conv, (cout, cin)) in enumerate(zip(convs, LEVEL_CONVOLUTIONS)):
        weight, bias = conv.fields.get("weight"), conv.fields.get("bias")
        shape = (cout, cin, KERNEL, KERNEL)
        if getattr(weight, "size", None) == math.prod(shape):   # SpatialConvolutionMM: 2-D
            weight = weight.reshape(shape)
        if getattr(weight, "shape", None) != shape or getattr(bias, "shape", None) != (cout,):
            got = (getattr(weight, "shape", None), getattr(bias, "shape", None))
            raise FormatError(path, f"convolution {i + 1} has weight and bias of shapes "
                                    f"{got[0]} and {got[1]}, expected {shape} and {(cout,)}")
        out.append((torch.from_numpy(weight).float(), torch.from_numpy(bias).float()))
    return out


def _collect_convolutions(obj, out: list) -> None:
    """Spatial convolutions of a Torch7 module tree, in the order they run."""
    if not isinstance(obj, Torch7Object):
        return
    if obj.class_name.split(".")[-1].startswith("SpatialConvolution"):
        out.append(obj)
        return
    modules = obj.fields.get("modules")
    if isinstance(modules, dict):
        keys = sorted(k for k in modules if isinstance(k, int))
        if obj.class_name.endswith("DataParallelTable"):
            keys = keys[:1]              # one replica per device; the first is the model
        for key in keys:
            _collect_convolutions(modules[key], out)


# -- registration -------------------------------------------------------------------------------

#: Where the SpyNet authors publish their Torch7 models (their repository at the commit
#: weathergen was written against).
SPYNET_URL = ("https://raw.githubusercontent.com/anuragranj/spynet/"
              "7c4a3f7d1a5879a50361fff3e1b8fa35ec397fcd/models/")
#: sha256 of the authors' Torch7 files (computed from their repository; none is published).
SPYNET_SHA256 = {
    "modelL1_3.t7": "a1c9a6d97a794cc6370e91693e3a3163ba809c03a93c4ccc1e8f2faa38896a23",
    "modelL1_4.t7": "0270a8377f033841d620787b1a89015de43adee786bfce3929ba8da9644e97b7",
    "modelL1_C.t7": "1c4c28ae0d37c1246aa5185456837b15620e2fcbf895948a65b34a1327fcc636",
    "modelL1_F.t7": "238ae30d824e25481115de5e83a5a58cd2f87406d6035db80c8fbc2c9962792a",
    "modelL1_K.t7": "753c5953bad64b2aa54d59ae21c4a30086f061010ebd6e958927bd6582342515",
    "modelL2_3.t7": "92c83a7a7e821b6a5143606de7a391bfef290fffaaada1abf54f43b62a497bd8",
    "modelL2_4.t7": "4e7fa57d23c7e5ac4116646cc0a5974bfa48084169a68cb2429b4ec3a1bf90dd",
    "modelL2_C.t7": "74ff1d8c5b3510412b56ec161aef4c0294012ab725c889c10644aefd813b071b",
    "modelL2_F.t7": "d3bd52b5e487359d4e10a5289f4510054302530b23dce76705890ce6c0938ddc",
    "modelL2_K.t7": "04d3779ba565bdedd52740c041498ed8d7e8929cfc8cfc388b5b25f74614738c",
    "modelL3_3.t7": "8b594ce991a50bee778323b10f6b20fbeefe0fc2242483d842b25c8208457833",
    "modelL3_4.t7": "907280d93de609b6ca424655b08c827b6b4d8f619a7140b0cd7abea5df142671",
    "modelL3_C.t7": "bb30f4ea4761dc5728a75fa2713e2a03f86fecb72f015747bd2166b487710d43",
    "modelL3_F.t7": "07ccf004cdc076acca6cee7b5278ca1dd6827e8dd253fdc0639291e11358d58a",
    "modelL3_K.t7": "18c878c323a8c77522c05ef57a569d63cd4557a50bb846ad52c34234989336b4",
    "modelL4_3.t7": "42916ebe21e2d7daac6e37c98c09cffd5546a26961e9376df7f21b686cad90cf",
    "modelL4_4.t7": "f5d54420bea029170799effe57de4a455d4c0448b48a88f50ddfdb4dd622269b",
    "modelL4_C.t7": "cb97a3d733eba355b10692905ba32d0e11294ef8565c64aa622bdfb343b22ab6",
    "modelL4_F.t7": "0114c6f13da56c284583f06fc5a5fd54696d83ec94730008f40b9cc8a314ef4f",
    "modelL4_K.t7": "4cdc83777113b9c70c3520bafce43ab47f3a46edc46526c2ec196089a012403e",
    "modelL5_3.t7": "a4a6741717512be22e6f79a15acc26295a86bbb9541ea896ad5d068c2dfd1cfc",
    "modelL5_4.t7": "4f863ce8e6f28f4c005875d66b2a25bd0cd32046633cf9d8d9b5973be579ae29",
    "modelL5_C.t7": "60cad2f17477a9537642aebb908750288c758956e5ad8517edd5db68b6a46a3e",
    "modelL5_F.t7": "f26501203e8fa1963d7eee609851a7a799935ca4fb1423127e13738ce2b10bc6",
    "modelL5_K.t7": "7ea4bbaaab4e18e7d0f6053a1c193eb1e305b3e720beff41272b7e5231b0ba16",
    "modelL6_C.t7": "7b346b1eeca9c8e244a0220cf5c6332281b84614a2be2718226a0415d22c4bd4",
    "modelL6_F.t7": "efce1c257e90ca0b0b7dabcef8c973f08dcac3e58b83c86e3629f71b107ca8eb",
    "modelL6_K.t7": "74180017986538d84a1d28658b7735135b5468f5f1bc3f6def8bd1773660c975",
}
SPYNET_LICENCE = ("the SpyNet authors' licence: non-commercial scientific research only, no "
                  "redistribution (github.com/anuragranj/spynet)")
#: Where the PyTorch port of SpyNet publishes its converted weights.
SNIKLAUS_URL = "http://content.sniklaus.com/github/pytorch-spynet/network-{}.pytorch"

register_model(ModelSpec(
    name="spynet", build=SpyNetModel, default_checkpoint="spynet-sintel-final",
    description="SpyNet (Ranjan and Black, CVPR 2017) as the paper ran it, 1.4M parameters"))
register_model(ModelSpec(
    name="spynet-sniklaus", build=SpyNetSniklausModel,
    default_checkpoint="spynet-sniklaus-sintel-final",
    description="SpyNet as the PyTorch port of S. Niklaus computes it, 1.4M parameters"))
for _variant, _letter in VARIANTS.items():
    _parts = tuple(dict.fromkeys(level_file_names(_letter)))
    register_checkpoint(CheckpointSpec(
        f"spynet-{_variant}", "spynet",
        f"SpyNet, the authors' {_variant} model (their per-level files)",
        url=SPYNET_URL, parts=_parts, pack=pack_level_files,
        part_sha256=tuple((p, SPYNET_SHA256[p]) for p in _parts), licence=SPYNET_LICENCE))
    register_checkpoint(CheckpointSpec(
        f"spynet-sniklaus-{_variant}", "spynet-sniklaus",
        f"SpyNet, the authors' {_variant} model as converted by the PyTorch port",
        url=SNIKLAUS_URL.format(_variant), licence=SPYNET_LICENCE))
