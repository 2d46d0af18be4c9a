"""docs/ is read by people: the pages written by hand stay within a size one can read, and no
page becomes the place where everything goes. The generated pages (docs/cli.md from --help,
docs/figures/ from the benchmarks) are not counted."""

from __future__ import annotations

from conftest import PROJECT_ROOT

DOCS = PROJECT_ROOT / "docs"
#: Every hand-written page of docs/ together, in bytes.
TOTAL_LIMIT = 250_000
#: The largest page, in bytes (docs/engine.md is the largest).
PAGE_LIMIT = 60_000
GENERATED = {"cli.md"}


def written_pages() -> dict[str, int]:
    """``{name: bytes}`` of every hand-written Markdown page directly in docs/."""
    return {p.name: len(p.read_bytes()) for p in sorted(DOCS.glob("*.md")) if p.name not in GENERATED}


def test_the_hand_written_docs_stay_within_their_size():
    pages = written_pages()
    assert "engine.md" in pages and len(pages) >= 8        # the walk found the pages
    total = sum(pages.values())
    assert total <= TOTAL_LIMIT, (f"docs/ (without cli.md and figures/) is {total} bytes; at most "
                                  f"{TOTAL_LIMIT}: {pages}")
    large = {name: size for name, size in pages.items() if size > PAGE_LIMIT}
    assert not large, f"pages over {PAGE_LIMIT} bytes: {large}"


def test_generated_pages_are_not_counted(tmp_path, monkeypatch):
    (tmp_path / "cli.md").write_bytes(b"x" * (TOTAL_LIMIT + 1))
    (tmp_path / "page.md").write_bytes(b"y" * 10)
    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / "bench.md").write_bytes(b"z" * (TOTAL_LIMIT + 1))
    monkeypatch.setattr(__import__(__name__), "DOCS", tmp_path)
    assert written_pages() == {"page.md": 10}
