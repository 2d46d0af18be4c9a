"""Figures by region and outlier rates of one pair and their means over pairs, by hand."""

from __future__ import annotations

import pytest
import torch

from weathergen.attack.figures import FIGURE_KEYS, mean_figures, region_figures


def hand_made():
    """gt u = [[10, 0, 0], [0, 100, 2]]; the weather flow errs by [[0.5, 2, 4], [6, 4, 3.5]] px
    along u; the clean flow differs from the weather flow by 3 px (v) where the weather covers
    the frame (the two left pixels of the top row) and by 1 px elsewhere."""
    gt = torch.zeros(2, 2, 3)
    gt[0] = torch.tensor([[10.0, 0, 0], [0, 100, 2]])
    weather = gt.clone()
    weather[0] += torch.tensor([[0.5, 2, 4], [6, 4, 3.5]])
    covered = torch.tensor([[True, True, False], [False, False, False]])
    clean = weather.clone()
    clean[1] += torch.where(covered, 3.0, 1.0)
    return clean[None], weather[None], covered, gt


def test_region_figures_by_hand():
    clean, weather, covered, gt = hand_made()
    got = region_figures(clean, weather, covered, gt)
    assert got["aee_weather_px"] == pytest.approx(3.0)
    assert got["aee_clear_px"] == pytest.approx(1.0)
    assert got["epe_weather_px"] == pytest.approx((0.5 + 2) / 2)
    assert got["epe_clear_px"] == pytest.approx((4 + 6 + 4 + 3.5) / 4)
    assert got["weather_coverage"] == pytest.approx(100 / 3)
    assert got["fl_all"] == pytest.approx(50.0)
    assert [got[f"outliers_{n}px"] for n in (1, 3, 5)] == pytest.approx([500 / 6, 400 / 6, 100 / 6])
    assert got["gt_valid_px"] == 6
    # Invalid ground truth leaves its pixel out of the EPE figures and rates, not of the AEE ones.
    valid = torch.tensor([[[True, True, True], [False, True, True]]])
    masked = region_figures(clean, weather, covered, gt, valid)
    assert masked["epe_clear_px"] == pytest.approx((4 + 4 + 3.5) / 3)
    assert masked["fl_all"] == pytest.approx(40.0) and masked["gt_valid_px"] == 5
    assert masked["aee_clear_px"] == pytest.approx(1.0)


def test_missing_regions_and_ground_truth_give_none():
    clean, weather, _, _ = hand_made()
    none = region_figures(clean, weather)                 # no weather (an Lp perturbation)
    assert none["aee_weather_px"] is None and none["weather_coverage"] == 0.0
    assert none["aee_clear_px"] == pytest.approx((3.0 * 2 + 1.0 * 4) / 6)   # every pixel
    for key in ("epe_weather_px", "epe_clear_px", "fl_all", "outliers_1px", "gt_valid_px"):
        assert none[key] is None, key
    everywhere = region_figures(clean, weather, torch.ones(2, 3, dtype=torch.bool))
    assert everywhere["aee_clear_px"] is None and everywhere["weather_coverage"] == 100.0


def test_means_pool_the_outlier_rates_over_valid_pixels():
    rows = [{**{k: None for k in FIGURE_KEYS}, "aee_weather_px": 3.0, "aee_clear_px": 1.0,
             "fl_all": 50.0, "outliers_1px": 10.0, "gt_valid_px": 6},
            {**{k: None for k in FIGURE_KEYS}, "aee_clear_px": 2.0, "fl_all": 10.0,
             "outliers_1px": 70.0, "gt_valid_px": 2},
            {**{k: None for k in FIGURE_KEYS}, "aee_clear_px": 0.0, "gt_valid_px": None}]
    got = mean_figures(rows)
    assert got["aee_weather_px"] == pytest.approx(3.0)            # the one pair that has it
    assert got["aee_clear_px"] == pytest.approx(1.0)
    assert got["fl_all"] == pytest.approx((50 * 6 + 10 * 2) / 8)   # pooled, as KITTI counts
    assert got["outliers_1px"] == pytest.approx((10 * 6 + 70 * 2) / 8)
    assert got["outliers_5px"] is None and set(got) == set(FIGURE_KEYS)


def test_the_records_of_a_pair_take_the_figures_from_one_declaration():
    """An evaluation's rows and an attack's pair summaries carry the figures of
    :func:`region_figures` through the one :class:`RegionFigures` they share: each field declared
    there once, filled from region_figures' keys, and written back by both."""
    from dataclasses import asdict, fields

    from weathergen.attack import EvalRow
    from weathergen.attack.figures import RegionFigures
    from weathergen.attack.figures import PairSummary

    clean, weather, covered, gt = hand_made()
    got = region_figures(clean, weather, covered, gt)
    assert set(got) == {f.name for f in fields(RegionFigures)}
    for record in (EvalRow("p", 1.0, **got),
                   PairSummary("p", 0, 1, 1.0, 1.0, 1.0, 1.0, **got)):
        assert isinstance(record, RegionFigures)
        assert {k: asdict(record)[k] for k in got} == got
    for cls in (EvalRow, PairSummary):
        own = [f.name for f in fields(cls) if f.name in cls.__dict__.get("__annotations__", {})]
        assert not set(own) & set(got), f"{cls.__name__} declares {set(own) & set(got)} again"
