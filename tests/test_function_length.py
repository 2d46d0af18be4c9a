"""Short parts: no function in weathergen/ and cli/ longer than 60 lines, no module longer than
600.

A function's length runs from its ``def`` line to its last line, docstring and comments
included (its decorators not); a method or a nested function counts on its own, and within the
function around it. A long function is split into helpers that read as the steps of what it does
(see docs/architecture.md).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = (ROOT / "weathergen", ROOT / "cli")
MAX_LINES = 60
MAX_MODULE_LINES = 600


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


def test_no_function_in_the_package_or_the_cli_is_longer_than_60_lines():
    files = sorted(path for source in SOURCES for path in source.rglob("*.py"))
    assert len(files) > 100                 # the walk found the package and the CLI
    found = [line for path in files for line in long_functions(path)]
    assert not found, (f"functions over {MAX_LINES} lines in weathergen/ and cli/ (split each "
                       f"into helpers that read as its steps):\n" + "\n".join(found))


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


def long_modules(folders: list[Path], limit: int = MAX_MODULE_LINES) -> dict[str, int]:
    """``{path: lines}`` of every Python module under ``folders`` longer than ``limit`` lines."""
    found = {}
    for folder in folders:
        for path in sorted(folder.rglob("*.py")):
            lines = len(path.read_text().splitlines())
            if lines > limit:
                found[path.relative_to(folder.parent).as_posix()] = lines
    return found


def test_no_module_is_longer_than_600_lines():
    found = long_modules(list(SOURCES))
    assert not found, (f"modules over {MAX_MODULE_LINES} lines (split them by concern):\n"
                       + "\n".join(f"{p}: {n} lines" for p, n in found.items()))


def test_the_module_check_counts_lines(tmp_path):
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "fits.py").write_text("x = 1\n" * 600)
    (tmp_path / "pkg" / "long.py").write_text("x = 1\n" * 601)
    assert long_modules([tmp_path / "pkg"]) == {"pkg/long.py": 601}
