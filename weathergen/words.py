"""Counts in words for messages: ``counted(1, "pair")`` is ``"1 pair"``, ``counted(3, "pair")``
``"3 pairs"``."""

from __future__ import annotations

from typing import Optional


def plural(noun: str, n: int, many: Optional[str] = None) -> str:
    """``noun`` as it reads after the number ``n``: ``"pair"`` for 1, ``"pairs"`` otherwise
    (``many``, where the plural is not the noun with an s)."""
    return noun if n == 1 else (many or noun + "s")


def counted(n: int, noun: str, many: Optional[str] = None) -> str:
    """``"1 pair"``, ``"3 pairs"``, ``"0 pairs"``: a count with its noun in the right number."""
    return f"{n} {plural(noun, n, many)}"
