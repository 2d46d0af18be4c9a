"""Flow tools: the Middlebury colour wheel and end-point errors, against hand-computed values."""

from __future__ import annotations

import math

import pytest
import torch

from weathergen.errors import ShapeError
from weathergen.flow import aee, color_wheel, epe, flow_to_color


def _constant(u: float, v: float, h: int = 2, w: int = 3) -> torch.Tensor:
    return torch.tensor([u, v]).view(2, 1, 1).expand(2, h, w).contiguous()


def _pixel(picture: torch.Tensor) -> tuple[int, int, int]:
    return tuple(int(c) for c in picture[:, 0, 0])


# -- colour wheel ---------------------------------------------------------------------------------

def test_wheel_has_the_55_benchmark_colours():
    wheel = color_wheel()
    assert wheel.shape == (55, 3)
    # Segment starts: red, yellow, green, cyan, blue, magenta (15, 6, 4, 11, 13, 6 colours).
    for index, rgb in [(0, (1, 0, 0)), (15, (1, 1, 0)), (21, (0, 1, 0)), (25, (0, 1, 1)),
                       (36, (0, 0, 1)), (49, (1, 0, 1))]:
        assert wheel[index].tolist() == list(map(float, rgb)), index
    assert wheel[1].tolist() == [1.0, math.floor(255 / 15) / 255, 0.0]


def test_directions_map_to_their_hues():
    # At full magnitude a vector shows its wheel colour: the angle of (-u, -v) on [-pi, pi]
    # picks position (angle/pi + 1)/2 * 54 on the wheel.
    right = _pixel(flow_to_color(_constant(1.0, 0.0)))
    assert right[0] == 255 and right[1] == 0 and right[2] < 50  # red
    assert _pixel(flow_to_color(_constant(-1.0, 0.0))) == (0, 209, 255)  # position 27: cyan-blue
    assert _pixel(flow_to_color(_constant(0.0, 1.0))) == (255, 229, 0)  # down, 13.5: yellow
    assert _pixel(flow_to_color(_constant(0.0, -1.0))) == (88, 0, 255)  # up, 40.5: violet


def test_zero_flow_is_white():
    picture = flow_to_color(torch.zeros(2, 4, 5))
    assert picture.dtype == torch.uint8 and picture.shape == (3, 4, 5)
    assert (picture == 255).all()


def test_saturation_grows_with_length_and_overflow_darkens():
    assert _pixel(flow_to_color(_constant(1.0, 0.0), max_magnitude=2.0)) == (255, 127, 127)
    assert _pixel(flow_to_color(_constant(3.0, 0.0), max_magnitude=2.0)) == (191, 0, 0)


def test_a_comparison_shares_one_scale():
    slow, fast = _constant(1.0, 0.0), _constant(2.0, 0.0, h=4, w=1)
    pictures = flow_to_color([slow, fast])
    assert isinstance(pictures, list) and len(pictures) == 2
    assert _pixel(pictures[0]) == (255, 127, 127)  # half the shared maximum
    assert _pixel(pictures[1]) == (255, 0, 0)
    assert _pixel(flow_to_color(slow)) == (255, 0, 0)  # on its own it sets the scale


def test_batches_keep_their_layout_and_non_finite_is_black():
    flows = torch.stack([_constant(1.0, 0.0), _constant(0.0, 0.0)])
    flows[0, 0, 1, 2] = float("nan")
    pictures = flow_to_color(flows)
    assert pictures.shape == (2, 3, 2, 3)
    assert pictures[0, :, 1, 2].tolist() == [0, 0, 0]
    assert _pixel(pictures[1]) == (255, 255, 255)


def test_colour_errors():
    with pytest.raises(ValueError, match=r"expected flow of shape \(2, H, W\)"):
        flow_to_color(torch.zeros(3, 4, 4))
    with pytest.raises(ValueError, match="max_magnitude"):
        flow_to_color(torch.zeros(2, 4, 4), max_magnitude=0.0)


# -- end-point errors ----------------------------------------------------------------------------

def _pair():
    flow = torch.zeros(2, 2, 1, 2)
    target = torch.zeros(2, 2, 1, 2)
    flow[0, :, 0, 0] = torch.tensor([3.0, 4.0])   # error 5
    flow[1, :, 0, 1] = torch.tensor([1.0, -1.0])  # error sqrt(2)
    target[1, :, 0, 0] = torch.tensor([0.0, 2.0])  # error 2
    return flow, target


def test_epe_and_aee_by_hand():
    flow, target = _pair()
    assert epe(flow, target).flatten().tolist() == pytest.approx([5.0, 0.0, 2.0, math.sqrt(2)])
    assert epe(flow, target).shape == (2, 1, 2)
    assert aee(flow, target).tolist() == pytest.approx([2.5, (2 + math.sqrt(2)) / 2])
    assert aee(flow[0], target[0]).item() == pytest.approx(2.5)
    assert aee(flow[0], target[0]).dim() == 0


def test_masks_select_pixels():
    flow, target = _pair()
    valid = torch.tensor([[[[True, False]]], [[[False, True]]]])  # (B, 1, H, W)
    per_pixel = epe(flow, target, valid).flatten().tolist()
    assert per_pixel == pytest.approx([5.0, 0.0, 0.0, math.sqrt(2)])
    assert aee(flow, target, valid).tolist() == pytest.approx([5.0, math.sqrt(2)])
    assert aee(flow, target, valid[:, 0]).tolist() == pytest.approx([5.0, math.sqrt(2)])
    nothing = torch.zeros(2, 1, 1, 2, dtype=torch.bool)
    assert torch.isnan(aee(flow, target, nothing)).all()


def test_epe_is_differentiable_even_at_zero_error_and_under_masked_nan():
    flow, target = _pair()
    target[0, :, 0, 1] = float("nan")  # an invalid ground-truth pixel
    valid = torch.isfinite(target).all(dim=1, keepdim=True)
    flow.requires_grad_()
    aee(flow, target, valid).sum().backward()
    assert torch.isfinite(flow.grad).all()
    # d|f - t|/df = (f - t)/|f - t| / (number of valid pixels): (3, 4)/5 at the only valid pixel.
    assert flow.grad[0, :, 0, 0].tolist() == pytest.approx([0.6, 0.8])
    assert flow.grad[0, :, 0, 1].tolist() == [0.0, 0.0]


def test_aee_gradcheck():
    flow = torch.randn(1, 2, 3, 4, dtype=torch.float64, requires_grad=True)
    target = torch.randn(1, 2, 3, 4, dtype=torch.float64)
    valid = torch.rand(1, 1, 3, 4) > 0.3
    valid[0, 0, 0, 0] = True
    assert torch.autograd.gradcheck(lambda f: aee(f, target, valid), (flow,))


def test_epe_errors():
    with pytest.raises(ValueError, match="target"):
        epe(torch.zeros(1, 2, 3, 4), torch.zeros(1, 2, 3, 5))
    with pytest.raises(ValueError, match="bool"):
        epe(torch.zeros(1, 2, 3, 4), torch.zeros(1, 2, 3, 4), torch.ones(1, 1, 3, 4))
    with pytest.raises(ValueError, match="valid mask of shape"):
        epe(torch.zeros(1, 2, 3, 4), torch.zeros(1, 2, 3, 4),
            torch.ones(1, 1, 4, 3, dtype=torch.bool))


# -- regions and outlier rates ----------------------------------------------------------------------

def _hand_made():
    """Ground truth u = [[10, 0, 0], [0, 100, 2]] (v = 0) and a flow off by errors of
    [[0.5, 2, 4], [6, 4, 3.5]] px along u."""
    gt = torch.zeros(2, 2, 3)
    gt[0] = torch.tensor([[10.0, 0, 0], [0, 100, 2]])
    flow = gt.clone()
    flow[0] += torch.tensor([[0.5, 2, 4], [6, 4, 3.5]])
    return flow, gt


def test_outlier_rates_by_hand():
    from weathergen.flow import fl_all, outlier_rate

    flow, gt = _hand_made()
    assert outlier_rate(flow, gt, 1.0).item() == pytest.approx(100 * 5 / 6)
    assert outlier_rate(flow, gt, 3.0).item() == pytest.approx(100 * 4 / 6)
    assert outlier_rate(flow, gt, 5.0).item() == pytest.approx(100 * 1 / 6)
    # Fl-all: above 3 px and above 5 % of |gt|; the 4 px error on the 100 px vector is no outlier.
    assert fl_all(flow, gt).item() == pytest.approx(100 * 3 / 6)
    valid = torch.tensor([[True, True, True], [False, True, True]])
    assert outlier_rate(flow, gt, 3.0, valid).item() == pytest.approx(100 * 3 / 5)
    assert fl_all(flow, gt, valid).item() == pytest.approx(100 * 2 / 5)
    batch = fl_all(torch.stack((flow, gt)), torch.stack((gt, gt)))
    assert batch.tolist() == pytest.approx([50.0, 0.0])
    assert math.isnan(fl_all(flow, gt, torch.zeros(2, 3, dtype=torch.bool)).item())


def test_weather_mask_takes_either_frame_above_one_level():
    from weathergen.flow import WEATHER_OPACITY_THRESHOLD, weather_mask

    assert WEATHER_OPACITY_THRESHOLD == pytest.approx(1 / 255)
    o1 = torch.tensor([[0.5, 0.0, 0.0], [0.0, 0.0, 0.0]])
    o2 = torch.tensor([[0.0, 0.01, 0.003], [0.0, 0.0, 1.0]])
    assert weather_mask(o1, o2).tolist() == [[True, True, False], [False, False, True]]
    assert weather_mask(o1).tolist() == [[True, False, False], [False, False, False]]
    assert weather_mask(o1, o2, threshold=0.002).tolist() == [[True, True, True],
                                                             [False, False, True]]
    with pytest.raises(ShapeError):
        weather_mask(o1, o2[None])
