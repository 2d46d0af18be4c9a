"""GMA, FlowFormer and both SpyNets compute the same function as their reference implementations.

tests/models/reference_flows.npz holds flows that the reference code computed (made by
scripts/make_reference_flows.py) with reproducible random weights on reproducible random frames;
our networks get the same weights and frames here. FlowFormer and the SpyNets are compared in
float64 (agreement to rounding), GMA in float32 as its correlation is computed in float32 by
design. The paper's SpyNet is compared with the research code's (its padding included), the
port's SpyNet with the port's network.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from model_layouts import seeded_images, seeded_weights, spynet_weights
from weathergen.models import build_model

GOLDEN = Path(__file__).resolve().parent / "reference_flows.npz"
# Settings of scripts/make_reference_flows.py.
GMA_SEED, GMA_SIZE, GMA_ITERS = 1, (128, 144), 3
FF_SEED, FF_SIZE, FF_ITERS = 2, (64, 80), 3
SPYNET_SEED, SPYNET_SIZE = 3, (72, 100)
SNIKLAUS_SEED, SNIKLAUS_SIZE = 4, (64, 96)


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


@pytest.mark.parametrize("arch, key, seed, size", [
    ("spynet", "spynet", SPYNET_SEED, SPYNET_SIZE),
    ("spynet-sniklaus", "spynet_sniklaus", SNIKLAUS_SEED, SNIKLAUS_SIZE),
])
def test_spynets_match_their_reference_implementations(reference, arch, key, seed, size):
    model = build_model(arch).double()
    model.network.load_state_dict(spynet_weights(model.network.state_dict(), seed))
    x1, x2 = seeded_images(seed, *size)
    with torch.no_grad():
        flow = model(x1, x2)[0].numpy()
    expected = reference[key]
    assert np.abs(expected).max() > 1.0
    np.testing.assert_allclose(flow, expected, atol=1e-9 * np.abs(expected).max())


def test_the_two_spynets_differ_on_the_same_weights(reference):
    """The paper's and the port's SpyNet are different functions of the same weights (pyramid
    depth, upsampling, warping): the port's network misses the research code's flow."""
    model = build_model("spynet-sniklaus").double()
    model.network.load_state_dict(spynet_weights(model.network.state_dict(), SPYNET_SEED))
    x1, x2 = seeded_images(SPYNET_SEED, *SPYNET_SIZE)
    with torch.no_grad():
        flow = model(x1, x2)[0].numpy()
    assert np.abs(flow - reference["spynet"]).max() > 0.1
