"""The robust rigid fit of the camera motion, on synthetic stereo correspondences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from weathergen.datasets.posefit import fit_camera_motion, kabsch, stereo_residuals
from weathergen.geometry import rotation_angle_deg

K = np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]])
BASELINE = 0.54


def rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.deg2rad(deg)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * cross + (1 - np.cos(a)) * cross @ cross


def motion(axis=(0.1, 1.0, 0.05), deg=1.7, t=(0.05, -0.02, -0.9)):
    out = np.eye(4)
    out[:3, :3] = rotation(axis, deg)
    out[:3, 3] = t
    return out


def scene_points(n, rng):
    return np.c_[rng.uniform(-15, 15, n), rng.uniform(-2.5, 1.5, n), rng.uniform(4, 70, n)]


def errors(estimate, truth):
    rot = float(rotation_angle_deg(torch.from_numpy(estimate[:3, :3] @ truth[:3, :3].T)))
    return rot, float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))


def test_kabsch_recovers_an_exact_transform_with_and_without_weights():
    rng = np.random.default_rng(0)
    truth = motion()
    src = scene_points(50, rng)
    dst = src @ truth[:3, :3].T + truth[:3, 3]
    np.testing.assert_allclose(kabsch(src, dst), truth, atol=1e-10)
    np.testing.assert_allclose(kabsch(src, dst, rng.uniform(0.1, 2, 50)), truth, atol=1e-10)


def test_kabsch_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    mirrored = src * [1, 1, -1]          # the best orthogonal map is a reflection
    rot = kabsch(src, mirrored)[:3, :3]
    assert np.linalg.det(rot) == pytest.approx(1.0)


def test_kabsch_rejects_too_few_points():
    with pytest.raises(ValueError, match="N >= 3"):
        kabsch(np.zeros((2, 3)), np.zeros((2, 3)))


def test_stereo_residuals_are_zero_for_the_true_motion_and_in_pixels():
    rng = np.random.default_rng(2)
    truth = motion()
    p1 = scene_points(100, rng)
    p2 = p1 @ truth[:3, :3].T + truth[:3, 3]
    assert stereo_residuals(truth, p1, p2, K, BASELINE).max() < 1e-9
    shifted = p2.copy()
    shifted[:, 0] += shifted[:, 2] / K[0, 0]          # exactly one pixel to the right
    np.testing.assert_allclose(stereo_residuals(truth, p1, shifted, K, BASELINE), 1.0, atol=1e-9)


@pytest.mark.parametrize("outliers", [0.0, 0.2, 0.4])
def test_fit_recovers_motion_despite_outliers(outliers):
    rng = np.random.default_rng(3)
    truth = motion()
    p1 = scene_points(4000, rng)
    p2 = p1 @ truth[:3, :3].T + truth[:3, 3]
    # measurement noise: a tenth of a pixel in u, v and disparity
    obs = np.c_[K[0, 0] * p2[:, 0] / p2[:, 2] + K[0, 2], K[1, 1] * p2[:, 1] / p2[:, 2] + K[1, 2],
                K[0, 0] * BASELINE / p2[:, 2]] + rng.normal(0, 0.1, (4000, 3))
    z = K[0, 0] * BASELINE / obs[:, 2]
    p2 = np.c_[(obs[:, 0] - K[0, 2]) * z / K[0, 0], (obs[:, 1] - K[1, 2]) * z / K[1, 1], z]
    bad = rng.random(4000) < outliers
    p2[bad] += rng.normal(0, 2.0, (int(bad.sum()), 3))
    fit = fit_camera_motion(p1, p2, K, BASELINE)
    rot_err, trans_err = errors(fit.cam2_from_cam1, truth)
    assert rot_err < 0.1
    assert trans_err < 0.02
    assert fit.inlier_fraction == pytest.approx(1 - outliers, abs=0.08)
    assert fit.rms_px < 0.5
    assert fit.summary()["points"] == 4000


def test_fit_is_deterministic():
    rng = np.random.default_rng(4)
    truth = motion()
    p1 = scene_points(500, rng)
    p2 = p1 @ truth[:3, :3].T + truth[:3, 3]
    p2[::3] += 1.0
    a, b = (fit_camera_motion(p1, p2, K, BASELINE, seed=7) for _ in range(2))
    np.testing.assert_array_equal(a.cam2_from_cam1, b.cam2_from_cam1)
    np.testing.assert_array_equal(a.inliers, b.inliers)


def test_fit_of_unrelated_points_has_few_inliers():
    rng = np.random.default_rng(5)
    fit = fit_camera_motion(scene_points(1000, rng), scene_points(1000, rng), K, BASELINE)
    assert fit.inlier_fraction < 0.2


def test_fit_rejects_bad_input():
    with pytest.raises(ValueError, match="at least 3"):
        fit_camera_motion(np.ones((2, 3)), np.ones((2, 3)), K, BASELINE)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fit_camera_motion(np.ones((5, 3)), np.ones((4, 3)), K, BASELINE)
