"""GMA and FlowFormer compute the same function as the authors' implementations.

tests/models/reference_flows.npz holds flows that the authors' code computed (made by
scripts/make_reference_flows.py) with reproducible random weights on reproducible random frames;
our networks get the same weights and frames here. FlowFormer is compared in float64 (agreement
to rounding), GMA in float32 as its correlation is computed in float32 by design.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from model_layouts import seeded_images, seeded_weights
from weathergen.models import build_model

GOLDEN = Path(__file__).resolve().parent / "reference_flows.npz"
# Settings of scripts/make_reference_flows.py.
GMA_SEED, GMA_SIZE, GMA_ITERS = 1, (128, 144), 3
FF_SEED, FF_SIZE, FF_ITERS = 2, (64, 80), 3


@pytest.fixture(scope="module")
def reference():
    return np.load(GOLDEN)


def test_gma_matches_the_authors_implementation(reference):
    model = build_model("gma", iters=GMA_ITERS)
    model.network.load_state_dict(seeded_weights(model.network.state_dict(), GMA_SEED))
    x1, x2 = seeded_images(GMA_SEED, *GMA_SIZE)
    with torch.no_grad():
        flow = model(x1.float(), x2.float())[0].numpy()
    expected = reference["gma"]
    assert np.abs(expected).max() > 1.0  # a non-trivial flow
    np.testing.assert_allclose(flow, expected, atol=5e-5 * np.abs(expected).max())


def test_flowformer_matches_the_authors_implementation(reference):
    model = build_model("flowformer", iters=FF_ITERS).double()
    model.network.load_state_dict(seeded_weights(model.network.state_dict(), FF_SEED))
    x1, x2 = seeded_images(FF_SEED, *FF_SIZE)
    with torch.no_grad():
        flow = model(x1, x2)[0].numpy()
    expected = reference["flowformer"]
    assert np.abs(expected).max() > 1.0
    np.testing.assert_allclose(flow, expected, atol=1e-9 * np.abs(expected).max())
