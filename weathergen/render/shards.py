"""Splitting a render over job arrays: shard ``i`` of ``N`` takes every N-th pair."""

from __future__ import annotations

from ..datasets import PairRef
from ..errors import ConfigError


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/N"`` with ``1 <= i <= N`` -> ``(i, N)``."""
    try:
        i_text, n_text = text.split("/")
        i, n = int(i_text), int(n_text)
    except ValueError:
        raise ConfigError(f"${{shard}} {text!r}: expected I/N, e.g. 2/8") from None
    if n < 1 or not 1 <= i <= n:
        raise ConfigError(f"${{shard}} {text!r}: I must be between 1 and N (got I={i}, N={n})")
    return i, n


def shard_refs(refs: list[PairRef], shard: tuple[int, int]) -> list[PairRef]:
    """The pairs of shard ``i`` of ``N``: every N-th pair of the sorted list, starting at ``i - 1``."""
    i, n = shard
    ordered = sorted(refs, key=lambda r: r.id)
    return ordered[i - 1::n]
