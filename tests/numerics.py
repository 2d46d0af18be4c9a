"""How closely two float32 results of one quantity, computed in two ways, must agree.

Two float32 computations of the same quantity that add in different orders (another instruction
set's vector width or blocking in oneDNN and ATen, another split between threads, a batch of
another size, a checkpointed recomputation) differ by rounding alone. Rounding does not respect an
element's own size: a sum of n float32 terms is off by at most about n · u · Σ|terms| and
typically by about √n · u · Σ|terms| (u = eps32 / 2, the unit roundoff; Higham, *Accuracy and
Stability of Numerical Algorithms*, 2nd ed., 2002, §4.2), and a network chains many such sums.
An element that is small because its terms cancel carries the absolute error of the large terms
it was made from, so an element-wise relative tolerance (``torch.allclose(rtol=...)`` with a tiny
``atol``) fails on such an element on one machine and passes on another. These comparisons bound
the largest difference by the largest magnitude of the values compared instead:

    max |actual − expected| ≤ k · eps32 · max |expected|

with ``k`` stated, and where it comes from, where it is used. For a network, :func:`rounding_k`
gives ``k`` from its structure: a sum of n terms whose order changes moves its result by about
√n · u of the result's size, and along a chain of L such sums (the layers the value passes,
forward, and back again for a gradient) these add up to at most L · √n · u, that is
k = L · √n / 2 with n the longest sum's length. That is hundreds of times what any instruction
set was seen to give (docs/architecture.md, "Tests"), and still a thousandth or less of what a
real mistake (a missed term, a stale value) changes. The inputs of such a comparison come from a
seeded generator of the test's own.
"""

from __future__ import annotations

import math

import torch

#: The spacing of float32 numbers at 1 (2⁻²³ ≈ 1.19e-7): twice the unit roundoff.
EPS32 = torch.finfo(torch.float32).eps


def rounding_k(sums: int, terms: int) -> float:
    """``k`` for a value that passes ``sums`` reductions in a chain, the longest of ``terms``
    terms: ``sums · √terms / 2`` (see the module's docstring)."""
    return sums * math.sqrt(terms) / 2


def float32_gap(actual, expected) -> float:
    """``max|actual − expected| / (EPS32 · max|expected|)``: the largest difference in units of
    float32 spacing at the largest compared magnitude (``inf`` if ``expected`` is all zero and
    ``actual`` is not; 0 if both are). Tensors or arrays of one shape."""
    a = torch.as_tensor(actual).double()
    e = torch.as_tensor(expected).double()
    assert a.shape == e.shape, (a.shape, e.shape)
    diff = float((a - e).abs().max()) if a.numel() else 0.0
    scale = float(e.abs().max()) if e.numel() else 0.0
    if diff == 0.0:
        return 0.0
    return diff / (EPS32 * scale) if scale > 0 else float("inf")


def assert_float32_close(actual, expected, k: float, what: str = "") -> None:
    """``max|actual − expected| ≤ k · EPS32 · max|expected|`` (see the module's docstring);
    the message gives the gap found in those units."""
    gap = float32_gap(actual, expected)
    assert gap <= k, (f"{what + ': ' if what else ''}max|difference| = {gap:.3g} · eps32 · "
                      f"max|expected|, more than the {k:g} allowed")
