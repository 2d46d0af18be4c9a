"""Short functions in the engine: none in weathergen/engine/ is longer than 60 lines.

A function's length runs from its ``def`` line to its last line, docstring and comments
included (its decorators not); a method or a nested function counts on its own, and within the
function around it. A long function is split into helpers that read as the steps of what it does
(see docs/architecture.md).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENGINE = ROOT / "weathergen" / "engine"
MAX_LINES = 60


def long_functions(path: Path, limit: int = MAX_LINES) -> list[str]:
    """``FILE:LINE NAME: N lines`` for every function of ``path`` longer than ``limit`` lines,
    ``NAME`` qualified by its classes and functions (``_Plan.__init__``)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    found = []

    def visit(node: ast.AST, outer: tuple[str, ...]) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = (*outer, child.name)
                length = child.end_lineno - child.lineno + 1
                if not isinstance(child, ast.ClassDef) and length > limit:
                    found.append(f"{where}:{child.lineno} {'.'.join(name)}: {length} lines")
                visit(child, name)
            else:
                visit(child, outer)

    visit(tree, ())
    return found


def test_no_function_in_the_engine_is_longer_than_60_lines():
    files = sorted(ENGINE.rglob("*.py"))
    assert len(files) > 20                  # the walk found the engine
    found = [line for path in files for line in long_functions(path)]
    assert not found, (f"functions over {MAX_LINES} lines in weathergen/engine/ (split them into "
                       "helpers that read as its steps):\n" + "\n".join(found))


def test_the_length_check_names_file_function_and_length(tmp_path):
    """The check above sees a long function, a long method and a long nested function, counts
    the docstring and leaves a function of exactly 60 lines alone (a check that cannot fail
    proves nothing)."""
    def function(name: str, lines: int, indent: str = "") -> str:
        body = [f'{indent}    """Doc."""'] + [f"{indent}    x = {i}" for i in range(lines - 3)]
        return "\n".join([f"{indent}def {name}():", *body, f"{indent}    return x"])

    probe = tmp_path / "probe.py"
    probe.write_text("\n\n".join([
        "import torch",
        function("fits", 60),
        function("too_long", 61),
        "class Plan:\n" + function("__init__", 70, "    "),
        "def outer():\n" + function("inner", 62, "    ") + "\n    return inner",
        "@decorated\n" + function("decorated_fits", 60),
    ]) + "\n")
    found = long_functions(probe)
    assert [line.split(" ", 1)[1] for line in found] == [
        "too_long: 61 lines", "Plan.__init__: 70 lines", "outer: 64 lines",
        "outer.inner: 62 lines"], found
    assert found[0].startswith(f"{probe}:")
