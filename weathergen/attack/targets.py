"""What flow an attack pushes the network towards: zero, the negated benign flow, a constant,
or a flow read from a ``.flo`` file."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import torch

from ..errors import ConfigError
from ..io.sintel_formats import read_flo

@dataclass(frozen=True)
class TargetSpec:
    """What flow the attack pushes the network towards.

    kind: ``"zero"``, ``"negative"`` (minus the benign flow), ``"constant"`` (``value`` = (u, v)
    pixels) or ``"file"`` (a ``.flo`` at ``path``, read by the job runner).
    """

    kind: str
    value: tuple[float, float] = (0.0, 0.0)
    path: Optional[Path] = None

    def describe(self) -> str:
        if self.kind == "constant":
            return f"constant {self.value[0]:g},{self.value[1]:g}"
        if self.kind == "file":
            return f"file {self.path}"
        return self.kind


def parse_target(text: str) -> TargetSpec:
    """``zero`` | ``negative`` | ``U,V`` (pixels) | a path to a ``.flo`` file."""
    t = str(text).strip()
    if t in ("zero", "negative"):
        return TargetSpec(t)
    if "," in t and not t.lower().endswith(".flo"):
        parts = t.split(",")
        try:
            u, v = (float(p) for p in parts)
        except ValueError:
            raise ConfigError(f"${{target}} {text!r}: a constant target is two numbers U,V in "
                              "pixels, e.g. 0,-5") from None
        if not (math.isfinite(u) and math.isfinite(v)):
            raise ConfigError(f"${{target}} {text!r}: U and V must be finite")
        return TargetSpec("constant", (u, v))
    if t.lower().endswith(".flo"):
        return TargetSpec("file", path=Path(t))
    raise ConfigError(f"${{target}} {text!r}: expected zero, negative, U,V (pixels) or a .flo file")


def target_flow(spec: TargetSpec, benign: torch.Tensor,
                file_flow: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The target flow for one pair.

    Shape: benign (B, 2, H, W) pixels; file_flow (2, H, W) for ``kind == "file"``;
    returns (B, 2, H, W) on the benign flow's device, without gradient.
    """
    benign = benign.detach()
    if spec.kind == "zero":
        return torch.zeros_like(benign)
    if spec.kind == "negative":
        return -benign
    if spec.kind == "constant":
        value = torch.tensor(spec.value, dtype=benign.dtype, device=benign.device)
        return value.view(1, 2, 1, 1).expand_as(benign).clone()
    if spec.kind == "file":
        if file_flow is None:
            raise ValueError("a file target needs the flow read from the file")
        if tuple(file_flow.shape[-2:]) != tuple(benign.shape[-2:]):
            raise ConfigError(f"{spec.path}: target flow is {file_flow.shape[-1]}x"
                              f"{file_flow.shape[-2]} but the frames are {benign.shape[-1]}x"
                              f"{benign.shape[-2]}")
        return file_flow.to(benign).expand_as(benign).clone()
    raise ValueError(f"unknown target kind {spec.kind!r}")


def read_target_flow(path: str | Path) -> torch.Tensor:
    """A target flow file. Shape: returns (2, H, W) float32 pixels."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"${{target}} {path}: file not found")
    return torch.from_numpy(read_flo(path).transpose(2, 0, 1).copy())
