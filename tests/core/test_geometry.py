"""Projection and reprojection against hand-computed values."""

from __future__ import annotations

import math

import torch

from weathergen.geometry import (backproject, invert_rigid, project, reprojection_flow,
                                 rotation_angle_deg, transform_points)

K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 80.0, 40.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def test_project_hand_computed():
    pts = torch.tensor([[0.0, 0.0, 2.0], [1.0, -0.5, 2.0], [0.2, 0.4, 4.0]], dtype=torch.float64)
    pix, z = project(pts, K)
    # u = fx X/Z + cx, v = fy Y/Z + cy
    expected = torch.tensor([[50.0, 40.0], [100.0, 20.0], [55.0, 48.0]], dtype=torch.float64)
    torch.testing.assert_close(pix, expected)
    torch.testing.assert_close(z, pts[:, 2])


def test_backproject_then_project_is_identity():
    depth = torch.rand(1, 6, 9, dtype=torch.float64) + 0.5
    pts = backproject(depth, K)                       # (3, H, W)
    assert pts.shape == (3, 6, 9)
    pix, z = project(pts.flatten(1).T, K)
    torch.testing.assert_close(z, depth.flatten())
    assert torch.allclose(pix[:, 0], torch.arange(9, dtype=torch.float64).repeat(6))
    assert torch.allclose(pix[:, 1], torch.arange(6, dtype=torch.float64).repeat_interleave(9))


def test_translation_flow_of_a_plane():
    # Camera moves +0.5 along x: a point at depth 5 moves by -fx * 0.5 / 5 = -10 px in u.
    depth = torch.full((1, 4, 5), 5.0, dtype=torch.float64)
    cam2_from_cam1 = torch.eye(4, dtype=torch.float64)
    cam2_from_cam1[0, 3] = -0.5
    flow = reprojection_flow(depth, K, cam2_from_cam1)
    torch.testing.assert_close(flow[0], torch.full((4, 5), -10.0, dtype=torch.float64))
    torch.testing.assert_close(flow[1], torch.zeros(4, 5, dtype=torch.float64))


def test_rotation_about_y_moves_the_centre_pixel():
    # Rotating the camera by angle a about its y axis sends the optical-axis point to u = cx - fx tan(a)
    a = math.radians(5)
    rot = torch.eye(4, dtype=torch.float64)
    rot[0, 0] = rot[2, 2] = math.cos(a)
    rot[0, 2] = -math.sin(a)
    rot[2, 0] = math.sin(a)
    pix, _ = project(transform_points(rot, torch.tensor([[0.0, 0.0, 3.0]], dtype=torch.float64)), K)
    assert abs(pix[0, 0].item() - (50 - 100 * math.tan(a))) < 1e-9
    assert abs(rotation_angle_deg(rot[:3, :3]).item() - 5) < 1e-9


def test_invert_rigid():
    q = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64))[0]
    if torch.det(q) < 0:
        q[:, 0] *= -1
    t = torch.eye(4, dtype=torch.float64)
    t[:3, :3] = q
    t[:3, 3] = torch.tensor([1.0, -2.0, 0.5])
    torch.testing.assert_close(invert_rigid(t) @ t, torch.eye(4, dtype=torch.float64))
