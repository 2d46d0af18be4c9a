"""The bundled demo scene: exact geometry, real camera motion, deterministic output."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from weathergen.datasets import demo_pairs
from weathergen.datasets.demo import FRAMES, SCENES, write_demo_scene
from weathergen.geometry import reprojection_flow, rotation_angle_deg


@pytest.fixture(scope="module")
def pairs(demo_root):
    return demo_pairs()


def test_every_scene_has_the_expected_pairs(pairs):
    assert FRAMES >= 3
    assert sorted({p.id.scene for p in pairs}) == sorted(SCENES)
    assert len(pairs) == len(SCENES) * (FRAMES - 1)


def test_stored_flow_is_the_reprojection_through_depth_and_cameras(pairs):
    for pair in pairs:
        flow = reprojection_flow(pair.depth1.double(), pair.intrinsics, pair.cam2_from_cam1)
        err = (flow.float() - pair.flow).abs().max().item()
        # depth is stored as float32 (relative precision ~1e-7), the rest is exact
        assert err < 1e-3, f"{pair.id}: flow and reprojection differ by {err} px"
        assert pair.flow.abs().max() > 2, "the camera should move visibly"


def test_cameras_rotate_and_translate(pairs):
    for pair in pairs:
        rel = pair.cam2_from_cam1
        assert rotation_angle_deg(rel[:3, :3]).item() > 0.5
        assert torch.linalg.norm(rel[:3, 3]).item() > 0.1


def test_frames_are_textured_and_depth_is_plausible(pairs):
    for pair in pairs:
        assert pair.image1.std() > 0.05
        assert 1.0 < pair.depth1.min() and pair.depth1.max() < 40


def test_generation_is_deterministic(tmp_path, demo_root):
    write_demo_scene(tmp_path)
    def digest(root, rel):
        return hashlib.sha256((root / rel).read_bytes()).hexdigest()
    for rel in ("training/clean/street/frame_0002.png", "training/depth/courtyard/frame_0003.dpt",
                "training/flow/street/frame_0001.flo", "training/final/courtyard/frame_0001.png"):
        assert digest(tmp_path, rel) == digest(demo_root, rel), rel


def test_occlusion_masks_mark_disocclusions(demo_root):
    from weathergen.io.images import read_raw

    masks = [read_raw(p) for p in sorted((demo_root / "training/occlusions").rglob("*.png"))]
    assert masks
    frac = np.mean([(m > 0).mean() for m in masks])
    assert 0.0 < frac < 0.3
