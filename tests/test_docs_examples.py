"""Every ```python block of README.md and docs/*.md runs, so the examples cannot go stale.

The convention (docs/architecture.md, "Examples in the docs"): the blocks of one file run top to
bottom in one namespace (a block may use what an earlier block of the same file defined), in a
fresh temporary folder as the working directory (the released RAFT-small weights ship with the
package: ``get_model("raft-small")`` finds them); torch on one thread, on the CPU. Blocks work
on the bundled demo scene and on files they write themselves; a line for a real dataset goes in a
comment. What is not meant to run (a signature, printed output, JSON, a shell session) is fenced
as something other than python.
"""

from __future__ import annotations

import re

import pytest
import torch

from conftest import PROJECT_ROOT

DOCUMENTS = [PROJECT_ROOT / "README.md", *sorted((PROJECT_ROOT / "docs").glob("*.md"))]
_BLOCK = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.S | re.M)


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(line of the block's first code line, code)`` for every ```python block, in order."""
    return [(text.count("\n", 0, m.start(1)) + 1, m.group(1)) for m in _BLOCK.finditer(text)]


WITH_BLOCKS = [p for p in DOCUMENTS if python_blocks(p.read_text())]


def test_the_blocks_are_found_as_a_reader_sees_them():
    text = "intro\n```python\na = 1\n```\n\n```bash\nls\n```\n```python\nb = a + 1\n```\n"
    assert python_blocks(text) == [(3, "a = 1\n"), (10, "b = a + 1\n")]
    # every document with python in it is run; the README is one of them
    assert PROJECT_ROOT / "README.md" in WITH_BLOCKS and len(WITH_BLOCKS) >= 5


@pytest.fixture
def docs_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield tmp_path
    torch.set_num_threads(threads)


@pytest.mark.slow
@pytest.mark.parametrize("document", WITH_BLOCKS, ids=[p.name for p in WITH_BLOCKS])
def test_every_python_block_runs(document, docs_folder):
    namespace: dict = {"__name__": f"docs.{document.stem}"}
    for line, code in python_blocks(document.read_text()):
        # compiled at its own line numbers, so that a traceback points into the document
        compiled = compile("\n" * (line - 1) + code, str(document), "exec")
        try:
            exec(compiled, namespace)
        except Exception as exc:
            name = document.relative_to(PROJECT_ROOT)
            pytest.fail(f"{name}: the python block at line {line} fails: "
                        f"{type(exc).__name__}: {exc}", pytrace=True)
