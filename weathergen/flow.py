"""Flow tools: colour-wheel pictures of flow fields and end-point errors.

Flow follows the package convention: ``(2, H, W)`` or ``(B, 2, H, W)``, pixels, channel 0 is
``u`` (right), channel 1 is ``v`` (down). Valid masks are ``bool``, ``(1, H, W)`` / ``(B, 1, H, W)``
(the channel axis may be left out).

The colour coding is the one of the Middlebury flow benchmark (Baker et al., "A Database and
Evaluation Methodology for Optical Flow", IJCV 2011): the direction of a vector selects a hue on
a 55-colour wheel (red to the right, yellow down, cyan-blue to the left, blue-violet up) and its
length the saturation, from white at zero to the full hue at the maximum magnitude. Vectors longer
than the maximum keep their hue at 75 % brightness.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Union

import torch

from .errors import ShapeError

FlowOrFlows = Union[torch.Tensor, Sequence[torch.Tensor]]

# Hue segments of the wheel: number of colours and the colour each segment runs towards.
# The counts give the perceptually larger segments (red-yellow, cyan-blue, blue-magenta)
# more steps.
_SEGMENTS = [
    (15, (1.0, 0.0, 0.0), (1.0, 1.0, 0.0)),  # red -> yellow
    (6, (1.0, 1.0, 0.0), (0.0, 1.0, 0.0)),   # yellow -> green
    (4, (0.0, 1.0, 0.0), (0.0, 1.0, 1.0)),   # green -> cyan
    (11, (0.0, 1.0, 1.0), (0.0, 0.0, 1.0)),  # cyan -> blue
    (13, (0.0, 0.0, 1.0), (1.0, 0.0, 1.0)),  # blue -> magenta
    (6, (1.0, 0.0, 1.0), (1.0, 0.0, 0.0)),   # magenta -> red
]


def color_wheel() -> torch.Tensor:
    """The 55 colours of the Middlebury wheel as ``(55, 3)`` float64 RGB in ``[0, 1]``.

    Within a segment of ``n`` colours, colour ``i`` is ``i/n`` of the way from the segment's start
    to its end, quantised down to a multiple of 1/255 as in the benchmark's code.
    """
    rows = []
    for n, start, end in _SEGMENTS:
        for i in range(n):
            t = math.floor(255 * i / n) / 255
            rows.append([s + (e - s) * t for s, e in zip(start, end)])
    return torch.tensor(rows, dtype=torch.float64)


def flow_to_color(flows: FlowOrFlows, max_magnitude: Optional[float] = None) -> FlowOrFlows:
    """Colour-wheel pictures of one flow field, a batch, or a list of them on one shared scale.

    Args:
        flows: a tensor ``(2, H, W)`` or ``(B, 2, H, W)``, or a list of such tensors (any sizes)
            that belong to one comparison (e.g. benign, random-weather and adversarial flow).
        max_magnitude: the flow length, in pixels, that gets the full hue. ``None``: the largest
            finite length over everything in ``flows``, so all pictures share one scale.

    Returns:
        ``uint8`` RGB in the image layout: ``(3, H, W)`` for ``(2, H, W)``, ``(B, 3, H, W)`` for a
        batch, a list for a list. Zero flow is white; non-finite vectors are black.
    """
    is_list = isinstance(flows, (list, tuple))
    items = list(flows) if is_list else [flows]
    for i, f in enumerate(items):
        _check_flow(f, f"flows[{i}]" if is_list else "flow")
    if max_magnitude is None:
        max_magnitude = max((_max_length(f) for f in items), default=0.0)
    elif not (max_magnitude > 0 and math.isfinite(max_magnitude)):
        raise ValueError(f"expected max_magnitude > 0, got {max_magnitude}")
    # All-zero (or all non-finite) flow: any positive scale draws it white.
    scale = max_magnitude if max_magnitude > 0 else 1.0
    wheel = color_wheel()
    pictures = [_colorize(f, scale, wheel) for f in items]
    return pictures if is_list else pictures[0]


def _check_flow(flow: torch.Tensor, name: str) -> None:
    if not isinstance(flow, torch.Tensor):
        raise TypeError(f"expected {name} to be a torch.Tensor, got {type(flow).__name__}")
    if flow.dim() not in (3, 4) or flow.shape[-3] != 2:
        raise ShapeError(f"expected {name} of shape (2, H, W) or (B, 2, H, W), "
                         f"got {tuple(flow.shape)}")


def _max_length(flow: torch.Tensor) -> float:
    length = torch.linalg.vector_norm(flow.detach().double(), dim=-3)
    length = length[torch.isfinite(length)]
    return float(length.max()) if length.numel() else 0.0


def _colorize(flow: torch.Tensor, scale: float, wheel: torch.Tensor) -> torch.Tensor:
    flow = flow.detach().to("cpu", torch.float64)
    u, v = flow[..., 0, :, :], flow[..., 1, :, :]
    finite = torch.isfinite(u) & torch.isfinite(v)
    u = torch.where(finite, u, 0.0) / scale
    v = torch.where(finite, v, 0.0) / scale
    length = torch.sqrt(u * u + v * v)
    # Angle of the vector turned by half a circle, mapped from [-pi, pi] to [0, n - 1]:
    # +u lands on red (both ends of the wheel), -u on the cyan-blue in the middle.
    n = wheel.shape[0]
    position = (torch.atan2(-v, -u) / math.pi + 1) / 2 * (n - 1)
    k0 = position.floor().long().clamp(0, n - 1)
    k1 = (k0 + 1) % n
    frac = (position - k0).unsqueeze(-1)
    color = (1 - frac) * wheel[k0] + frac * wheel[k1]  # (..., H, W, 3)
    length = length.unsqueeze(-1)
    color = torch.where(length <= 1, 1 - length * (1 - color), 0.75 * color)
    color = torch.where(finite.unsqueeze(-1), color, 0.0)
    picture = torch.floor(255 * color).clamp(0, 255).to(torch.uint8)
    return picture.movedim(-1, -3).contiguous()


# ---------------------------------------------------------------------------------------------
# End-point errors
# ---------------------------------------------------------------------------------------------

def epe(flow: torch.Tensor, target: torch.Tensor,
        valid: Optional[torch.Tensor] = None) -> torch.Tensor:
    """End-point error per pixel: the Euclidean distance between two flow vectors, in pixels.

    Differentiable; the gradient where ``flow == target`` is zero (not NaN), and pixels outside
    ``valid`` get zero error and zero gradient, whatever their values (even NaN).

    Shape:
        flow, target: ``(B, 2, H, W)`` or ``(2, H, W)``.
        valid: ``bool``, ``(B, 1, H, W)`` / ``(B, H, W)`` (``(1, H, W)`` / ``(H, W)`` unbatched),
            or ``None`` for all pixels.
        returns: ``(B, H, W)`` (``(H, W)`` unbatched).
    """
    _check_pair(flow, target)
    diff = flow - target
    mask = _mask(valid, flow)
    if mask is not None:
        # Mask before the norm so that invalid pixels contribute no NaN to the gradient.
        diff = torch.where(mask.unsqueeze(-3), diff, torch.zeros((), dtype=diff.dtype,
                                                                 device=diff.device))
    # vector_norm has gradient zero at zero, where sqrt(sum of squares) has NaN.
    return torch.linalg.vector_norm(diff, dim=-3)


def aee(flow: torch.Tensor, target: torch.Tensor,
        valid: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Average end-point error over the (valid) pixels of each flow field, in pixels.

    Shape: as :func:`epe`; returns ``(B,)`` for batches, a 0-d tensor for one flow field.
    A field without valid pixels has AEE NaN.
    """
    errors = epe(flow, target, valid)
    mask = _mask(valid, flow)
    if mask is None:
        return errors.mean(dim=(-2, -1))
    count = mask.sum(dim=(-2, -1)).to(errors.dtype)
    return errors.sum(dim=(-2, -1)) / count


def _check_pair(flow: torch.Tensor, target: torch.Tensor) -> None:
    _check_flow(flow, "flow")
    if target.shape != flow.shape:
        raise ShapeError(f"expected target of the flow's shape {tuple(flow.shape)}, "
                         f"got {tuple(target.shape)}")


def _mask(valid: Optional[torch.Tensor], flow: torch.Tensor) -> Optional[torch.Tensor]:
    """``valid`` as a bool tensor of the flow's shape without the channel axis, or None."""
    if valid is None:
        return None
    if valid.dtype != torch.bool:
        raise ShapeError(f"expected a bool valid mask, got {valid.dtype}")
    spatial = flow.shape[:-3] + flow.shape[-2:]
    if valid.dim() == flow.dim() and valid.shape[-3] == 1:
        valid = valid.squeeze(-3)
    if valid.shape != spatial:
        with_channel = tuple(flow.shape[:-3]) + (1,) + tuple(flow.shape[-2:])
        raise ShapeError(f"expected a valid mask of shape {with_channel} or {tuple(spatial)}, "
                         f"got {tuple(valid.shape)}")
    return valid


# ---------------------------------------------------------------------------------------------
# Figures by region and outlier rates
# ---------------------------------------------------------------------------------------------

#: Opacity above which a pixel counts as covered by weather: one 8-bit level (a white particle
#: with additive blending brightens such a pixel by at least one step of an 8-bit frame).
WEATHER_OPACITY_THRESHOLD = 1.0 / 255.0


def weather_mask(opacity1: torch.Tensor, opacity2: Optional[torch.Tensor] = None,
                 threshold: float = WEATHER_OPACITY_THRESHOLD) -> torch.Tensor:
    """The pixels the weather covers: opacity above ``threshold`` in frame 1 or in frame 2 (the
    flow at a pixel of frame 1 looks at both frames).

    Shape: opacities ``(B, 1, H, W)``, ``(1, H, W)`` or ``(H, W)``, both alike; returns ``bool``
    of the same shape.
    """
    covered = opacity1 > threshold
    if opacity2 is not None:
        if opacity2.shape != opacity1.shape:
            raise ShapeError(f"expected opacity2 of opacity1's shape {tuple(opacity1.shape)}, "
                             f"got {tuple(opacity2.shape)}")
        covered = covered | (opacity2 > threshold)
    return covered


def outlier_rate(flow: torch.Tensor, target: torch.Tensor, threshold_px: float,
                 valid: Optional[torch.Tensor] = None,
                 relative: Optional[float] = None) -> torch.Tensor:
    """Percentage of the (valid) pixels whose end-point error exceeds ``threshold_px`` pixels
    (and, with ``relative``, also ``relative`` times the length of the target vector).

    Shape: as :func:`aee`; returns ``(B,)`` for batches, 0-d for one field, in percent; NaN for a
    field without valid pixels.
    """
    errors = epe(flow, target, valid)
    bad = errors > threshold_px
    if relative is not None:
        bad = bad & (errors > relative * torch.linalg.vector_norm(target, dim=-3))
    mask = _mask(valid, flow)
    if mask is None:
        return 100.0 * bad.to(errors.dtype).mean(dim=(-2, -1))
    bad = bad & mask
    count = mask.sum(dim=(-2, -1)).to(errors.dtype)
    return 100.0 * bad.sum(dim=(-2, -1)).to(errors.dtype) / count


def fl_all(flow: torch.Tensor, target: torch.Tensor,
           valid: Optional[torch.Tensor] = None) -> torch.Tensor:
    """KITTI's Fl-all: the percentage of valid pixels whose end-point error exceeds both 3 px and
    5 % of the ground-truth vector's length. Shape: as :func:`outlier_rate`."""
    return outlier_rate(flow, target, 3.0, valid, relative=0.05)
