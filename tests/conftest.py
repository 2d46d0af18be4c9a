"""Shared fixtures: an isolated cache (so the demo scene is generated fresh), tiny fake datasets;
a fixed global seed before every test, and an opt-in shuffled order (``--shuffle-seed N``)."""

from __future__ import annotations

import os
import random
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

_CACHE = None


#: The seed of torch's, NumPy's and Python's global generators at the start of every test.
GLOBAL_SEED = 0


def pytest_addoption(parser):
    group = parser.getgroup("weathergen")
    group.addoption("--shuffle-seed", type=int, default=None, metavar="N",
                    help="run the tests in an order shuffled with seed N (the files in a shuffled "
                         "order, and the tests of each file in a shuffled order; with "
                         "--shuffle-tests, every test anywhere): a test that depends on the "
                         "tests before it fails in some order")
    group.addoption("--shuffle-tests", action="store_true",
                    help="with --shuffle-seed: shuffle all tests together, not file by file "
                         "(module fixtures are then set up again each time their file comes up)")


def pytest_configure(config):
    global _CACHE
    _CACHE = tempfile.mkdtemp(prefix="weathergen-test-cache-")
    os.environ["WEATHERGEN_CACHE"] = _CACHE
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # pytest-xdist (`make test` runs two workers): one thread each, so that the workers
        # share the cores rather than each asking torch for all of them
        import torch

        torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    """Shuffle the order with ``--shuffle-seed``; tests marked ``cuda`` skip where there is no
    CUDA device (``make gpu-check`` runs them)."""
    import torch

    seed = config.getoption("--shuffle-seed")
    if seed is not None:
        items[:] = shuffled(items, seed, config.getoption("--shuffle-tests"))
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (make gpu-check runs it on one)")
    for item in items:
        if item.get_closest_marker("cuda"):
            item.add_marker(skip)


def shuffled(items: list, seed: int, across_files: bool) -> list:
    """``items`` in an order drawn from ``seed`` alone (the same in every pytest-xdist worker):
    every item anywhere if ``across_files``, else the files in a random order and each file's
    items in a random order."""
    rng = random.Random(seed)
    if across_files:
        order = list(items)
        rng.shuffle(order)
        return order
    files: dict = {}
    for item in items:
        files.setdefault(item.nodeid.split("::")[0], []).append(item)
    groups = list(files.values())
    rng.shuffle(groups)
    for group in groups:
        rng.shuffle(group)
    return [item for group in groups for item in group]


def pytest_report_header(config):
    seed = config.getoption("--shuffle-seed")
    if seed is not None:
        across = "all tests together" if config.getoption("--shuffle-tests") else "file by file"
        return f"weathergen: tests in an order shuffled with seed {seed} ({across})"
    return None


@pytest.fixture(autouse=True)
def _fixed_global_state():
    """Every test starts from the same global state, whatever ran before it: torch's, NumPy's
    and Python's global generators seeded with ``GLOBAL_SEED``; torch's thread count, default
    dtype and gradient mode are put back afterwards (a command run in-process may set the
    thread count, and the number of threads changes how float sums are split)."""
    import torch

    threads, dtype, grad = torch.get_num_threads(), torch.get_default_dtype(), torch.is_grad_enabled()
    torch.manual_seed(GLOBAL_SEED)
    np.random.seed(GLOBAL_SEED)
    random.seed(GLOBAL_SEED)
    yield
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    torch.set_default_dtype(dtype)
    torch.set_grad_enabled(grad)


def pytest_unconfigure(config):
    if _CACHE:
        shutil.rmtree(_CACHE, ignore_errors=True)


PROJECT_ROOT = Path(__file__).resolve().parents[1]
#: The released RAFT-small checkpoint (sha256 c7d41b9c...), shipped with its BSD-3 licence in
#: tests/data/ so that a fresh clone tests everything.
RAFT_SMALL_WEIGHTS = PROJECT_ROOT / "tests" / "data" / "raft-small.pth"


@pytest.fixture(scope="session")
def raft_small_weights() -> Path:
    """The released RAFT-small weights (part of the repository: missing means a broken checkout)."""
    if not RAFT_SMALL_WEIGHTS.is_file():
        raise FileNotFoundError(f"{RAFT_SMALL_WEIGHTS} is missing: the released RAFT-small weights "
                                f"are part of the repository (git checkout -- tests/data)")
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
