"""Lessons from real KITTI frames, on data the tests make: a lens darkens the sky's corners, a
laser return lands far from its surface, and a coarse fill must not paste a near object's depth
in blocks over what stands behind it."""

from __future__ import annotations

import numpy as np

from weathergen.datasets.densify import fill_sparse
from weathergen.datasets.depth import complete_depth, estimate_sky, stray_measurements
from weathergen.framepair import COMPLETED, MEASURED


def _vignetted_street(h=120, w=240, seed=0):
    """A blue sky over the top third, darkened towards the corners like a real lens (to 70 %),
    over a textured ground measured by a scan every 3 rows."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 6) / (h / 2)) ** 2
    shade = 1 - 0.3 * np.clip(r2 / 2, 0, 1) ** 0.7
    image = np.empty((h, w, 3), np.float32)
    image[:] = np.array([0.55, 0.8, 1.0], np.float32)
    image *= shade[..., None]
    ground = yy >= h // 3
    image[ground] = rng.uniform(0.35, 0.75, (int(ground.sum()), 1)) * np.array([1, 1, 0.97])
    measured = ground & ((yy - h // 3) % 3 == 0)
    return image, measured, ~ground


def test_the_sky_darkened_in_the_corners_by_the_lens_is_still_sky():
    image, measured, sky_true = _vignetted_street()
    grey = image @ np.array([0.299, 0.587, 0.114], np.float32)
    corner = (slice(0, 6), slice(0, 6))
    assert grey[corner].max() < np.quantile(grey, 0.6)          # darker than the frame's bright share
    sky = estimate_sky(image, measured)
    assert sky[corner].all() and sky[0, -6:].all()
    assert sky[sky_true].mean() > 0.97 and not sky[~sky_true].any()


def test_a_stray_laser_return_keeps_its_pixel_but_seeds_no_fill():
    h, w = 60, 80
    image = np.full((h, w, 3), 0.3, np.float32)
    measured = np.zeros((h, w), bool)
    measured[::3, ::3] = True
    depth = np.full((h, w), 50.0, np.float32)
    depth[30, 42] = 10.0                                  # a return from a car, projected on a tree
    assert stray_measurements(1 / depth, measured)[30, 42]
    assert stray_measurements(1 / depth, measured).sum() == 1
    out, prov = complete_depth(depth, measured, image, far_depth=1000.0, estimate=False)
    assert prov[30, 42] == MEASURED and out[30, 42] == 10.0
    around = np.zeros((h, w), bool)
    around[26:35, 38:47] = True
    around[30, 42] = False
    assert (prov[around & ~measured] == COMPLETED).all()
    assert np.abs(out[around] - 50.0).max() < 0.5


def test_a_coarse_fill_does_not_paste_a_near_object_over_what_is_behind_it():
    """Trees (dark green, 60 m, measured on two rows far above) behind a white car (15 m, measured
    densely) whose roof is 14 px below them: the gap between is filled coarse to fine, and each
    tree pixel there takes the trees' depth, not the car's."""
    h, w = 96, 160
    image = np.zeros((h, w, 3), np.float32)
    image[:] = (0.15, 0.3, 0.12)                          # trees
    image[60:, 40:120] = (0.95, 0.95, 0.95)               # the car
    inverse = np.full((h, w), 1 / 60, np.float32)
    inverse[60:, 40:120] = 1 / 15
    measured = np.zeros((h, w), bool)
    measured[60:, 40:120] = True
    measured[[10, 14], :] = True
    filled, known = fill_sparse(inverse, measured, image, max_gap_px=48)
    trees = known & ~measured & (np.arange(h)[:, None] < 60)
    assert trees[30:60, 40:120].all()
    depth = 1 / filled[trees]
    assert np.abs(depth - 60).max() < 6, f"tree pixels took {depth.min():.1f} m"


def test_the_sky_seen_inside_a_sign_gantry_is_sky_and_a_grey_panel_there_is_not():
    """Sky the top border does not reach (framed by a dark gantry above the scanner) is still sky;
    a smooth pale grey panel framed the same way is not."""
    image, measured, sky_true = _vignetted_street()
    frame = np.zeros(sky_true.shape, bool)
    frame[4:34, 20:110] = True
    frame[8:30, 24:60] = False                   # sky seen through the gantry
    frame[8:30, 70:106] = False                  # a panel
    image[frame] = (0.1, 0.1, 0.12)
    image[8:30, 70:106] = (0.85, 0.85, 0.85)
    sky = estimate_sky(image, measured)
    assert sky[10:28, 26:58].all()
    assert not sky[8:30, 70:106].any() and not sky[frame].any()
