"""Shared fixtures: an isolated cache (so the demo scene is generated fresh), tiny fake datasets."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

_CACHE = None


def pytest_configure(config):
    global _CACHE
    _CACHE = tempfile.mkdtemp(prefix="weathergen-test-cache-")
    os.environ["WEATHERGEN_CACHE"] = _CACHE


def pytest_collection_modifyitems(config, items):
    """Tests marked ``cuda`` skip where there is no CUDA device (``make gpu-check`` runs them)."""
    import torch

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (make gpu-check runs it on one)")
    for item in items:
        if item.get_closest_marker("cuda"):
            item.add_marker(skip)


def pytest_unconfigure(config):
    if _CACHE:
        shutil.rmtree(_CACHE, ignore_errors=True)


PROJECT_ROOT = Path(__file__).resolve().parents[1]
#: The released RAFT-small checkpoint (sha256 c7d41b9c...), shipped with its BSD-3 licence as
#: package data in weathergen/models/weights/ (found by the name ``raft-small``).
RAFT_SMALL_WEIGHTS = PROJECT_ROOT / "weathergen" / "models" / "weights" / "raft-small.pth"


@pytest.fixture(scope="session")
def raft_small_weights() -> Path:
    """The released RAFT-small weights (part of the repository: missing means a broken checkout)."""
    if not RAFT_SMALL_WEIGHTS.is_file():
        raise FileNotFoundError(f"{RAFT_SMALL_WEIGHTS} is missing: the released RAFT-small weights "
                                f"are part of the repository (git checkout -- weathergen/models/weights)")
    return RAFT_SMALL_WEIGHTS


@pytest.fixture(scope="session")
def demo_root():
    from weathergen.datasets.demo import demo_root as make

    return make()


def write_fake_sintel(root: Path, scenes=("alley", "bamboo"), frames=4, size=(12, 16), seed=0,
                      test_split=True) -> Path:
    """A tiny Sintel tree: random frames, a fronto-parallel plane per frame, known cameras, flow."""
    from weathergen.io.images import write_png
    from weathergen.io.sintel_formats import write_cam, write_dpt, write_flo

    rng = np.random.default_rng(seed)
    h, w = size
    k = np.array([[20.0, 0, (w - 1) / 2], [0, 20.0, (h - 1) / 2], [0, 0, 1]])
    for s_i, scene in enumerate(scenes):
        for i in range(1, frames + 1):
            name = f"frame_{i:04d}"
            for p in ("clean", "final"):
                write_png(root / "training" / p / scene / f"{name}.png", rng.random((h, w, 3)))
            write_dpt(root / "training" / "depth" / scene / f"{name}.dpt",
                      np.full((h, w), 2.0 + s_i + 0.1 * i, np.float32))
            e = np.eye(4)[:3]
            e[:, 3] = [-0.1 * i, 0.0, 0.05 * i]
            write_cam(root / "training" / "camdata_left" / scene / f"{name}.cam", k, e)
            if i < frames:
                write_flo(root / "training" / "flow" / scene / f"{name}.flo",
                          rng.standard_normal((h, w, 2)).astype(np.float32))
            if test_split:
                write_png(root / "test" / "clean" / scene / f"{name}.png", rng.random((h, w, 3)))
    return root


@pytest.fixture
def fake_sintel(tmp_path):
    return write_fake_sintel(tmp_path / "sintel")
