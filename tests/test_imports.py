"""The import structure: every import at the top of its module, and no import cycles.

Tools that follow imports (and readers) then see every dependency of a module in its first lines.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"weathergen": ROOT / "weathergen", "weathergen.cli": ROOT / "cli"}


def _modules() -> dict[str, Path]:
    out = {}
    for package, folder in SOURCES.items():
        for path in sorted(folder.rglob("*.py")):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            name = ".".join([package, *parts])
            if package == "weathergen" and name.startswith("weathergen.cli"):
                continue
            out[name] = path
    return out


MODULES = _modules()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _import_stem(node: ast.ImportFrom, base: str) -> str:
    """The absolute module a ``from ... import`` statement reads from (``base``: the package the
    importing module sits in)."""
    if not node.level:
        return node.module or ""
    anchor = base.split(".")
    anchor = anchor[:len(anchor) - (node.level - 1)]
    return ".".join(anchor + ([node.module] if node.module else []))


def _imports(name: str) -> list[tuple[str, int, bool]]:
    """(imported module, line, at module level) for every import of weathergen in ``name``."""
    tree = ast.parse(MODULES[name].read_text())
    top = {id(node) for node in tree.body}
    base = name if _is_package(name) else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            stem = _import_stem(node, base)
            targets = [stem]
            # "from .pkg import module" imports a module, not only a name
            targets += [f"{stem}.{a.name}" for a in node.names if f"{stem}.{a.name}" in MODULES]
        else:
            continue
        for target in targets:
            if target.startswith("weathergen"):
                found.append((target, node.lineno, id(node) in top))
    return found


def test_every_import_is_at_the_top_of_its_module():
    inside = [f"{MODULES[name].relative_to(ROOT)}:{line} imports {target}"
              for name in MODULES for target, line, at_top in _imports(name) if not at_top]
    assert not inside, "imports inside functions:\n" + "\n".join(inside)


def _graph() -> dict[str, set[str]]:
    graph = {}
    for name in MODULES:
        edges = set()
        for target, _, _ in _imports(name):
            # importing a.b.c runs a/__init__ and a/b/__init__ first, unless the importer is
            # inside them already
            parts = target.split(".")
            for i in range(1, len(parts) + 1):
                module = ".".join(parts[:i])
                if module in MODULES and module != name and not name.startswith(module + "."):
                    edges.add(module)
        graph[name] = edges
    return graph


def test_there_is_no_import_cycle():
    graph = _graph()
    state: dict[str, int] = {}
    cycles = []

    def visit(node, path):
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(path[path.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, path + [nxt])
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


@pytest.mark.parametrize("module", ["weathergen.engine"])
def test_packages_resolve_their_names_at_import(module):
    import importlib

    mod = importlib.import_module(module)
    assert not hasattr(mod, "__getattr__"), f"{module} resolves names lazily"
    for name in mod.__all__:
        assert name in vars(mod), f"{module}.{name} is not imported at the top"


#: The layers of docs/architecture.md, lowest first; a package imports only lower layers.
LAYERS = [("weathergen", "weathergen.errors", "weathergen.workers", "weathergen.words"),
          ("weathergen.framepair", "weathergen.geometry", "weathergen.flow", "weathergen.io",
           "weathergen.execution", "weathergen.memory"),
          ("weathergen.datasets", "weathergen.models", "weathergen.engine"),
          ("weathergen.training",),
          ("weathergen.outputs",), ("weathergen.jobs",), ("weathergen.render",), ("weathergen.attack",),
          ("weathergen.benchmark",),
          ("weathergen.cli",), ("weathergen.__main__",)]


def test_each_layer_imports_only_the_layers_below_it():
    rank = {package: i for i, layer in enumerate(LAYERS) for package in layer}

    def package(module):
        return module if module in rank else ".".join(module.split(".")[:2])

    upward = [f"{a} imports {b}" for a, targets in _graph().items() for b in targets
              if package(a) != package(b) and rank[package(a)] <= rank[package(b)]]
    assert not upward, "imports that do not go down a layer:\n" + "\n".join(upward)


def _private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _private_uses(name: str) -> list[str]:
    """Private names of another weathergen module that ``name`` reaches: ``from .x import _y``,
    ``from . import _x`` (a private module is private to its package) and ``x._y`` where ``x``
    is a weathergen module bound by an import."""
    tree = ast.parse(MODULES[name].read_text())
    base = name if _is_package(name) else name.rpartition(".")[0]
    found, modules = [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            stem = _import_stem(node, base)
            if not stem.startswith("weathergen"):
                continue
            for alias in node.names:
                if f"{stem}.{alias.name}" in MODULES:
                    modules[alias.asname or alias.name] = f"{stem}.{alias.name}"
                if _private(alias.name):
                    found.append(f"line {node.lineno}: from {stem} import {alias.name}")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("weathergen"):
                    modules[alias.asname or alias.name.split(".")[0]] = alias.name
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            root = node.value
            if isinstance(root, ast.Name) and root.id in modules:
                found.append(f"line {node.lineno}: {root.id}.{node.attr}")
    return found


def test_no_module_uses_a_private_name_of_another():
    """A leading underscore means "this module's own": another module that needs the name
    needs it made public (or moved to where both can see it)."""
    uses = [f"{MODULES[name].relative_to(ROOT)} {use}" for name in MODULES
            for use in _private_uses(name)]
    assert not uses, "private names used across modules:\n" + "\n".join(uses)


def test_private_name_check_catches_both_forms(tmp_path, monkeypatch):
    """The check above sees both an imported private name and an attribute of an imported
    module (a check that cannot fail proves nothing)."""
    probe = tmp_path / "probe.py"
    probe.write_text("from .engine.renderer import _hidden\nfrom .engine import sampling\n"
                     "x = sampling._generator(0)\nfrom .engine import __version__\n")
    monkeypatch.setitem(MODULES, "weathergen.probe", probe)
    found = _private_uses("weathergen.probe")
    assert len(found) == 2 and "_hidden" in found[0] and "sampling._generator" in found[1], found


#: The readers of image files, and EXR's writer: in the layers from outputs/ up, only the frame
#: formats (weathergen/outputs/formats/) call them, so that a render's frames are written and
#: read back through one owner per format.
FRAME_FILE_FUNCTIONS = {"read_exr", "write_exr", "read_image", "read_image_kind", "read_raw"}
FRAME_OWNER = "weathergen.outputs.formats"


def _frame_file_uses(name: str) -> list[str]:
    """Imports of :data:`FRAME_FILE_FUNCTIONS` in module ``name``."""
    tree = ast.parse(MODULES[name].read_text())
    base = name if _is_package(name) else name.rpartition(".")[0]
    return [f"line {node.lineno}: {alias.name}" for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and _import_stem(node, base).startswith("weathergen")
            for alias in node.names if alias.name in FRAME_FILE_FUNCTIONS]


def test_the_format_registry_is_the_only_reader_of_frame_files():
    above = {p for layer in LAYERS[LAYERS.index(("weathergen.outputs",)):] for p in layer}
    uses = [f"{MODULES[name].relative_to(ROOT)} {use}" for name in MODULES
            if ".".join(name.split(".")[:2]) in above and not name.startswith(FRAME_OWNER)
            for use in _frame_file_uses(name)]
    assert not uses, ("frame files read or written outside weathergen/outputs/formats/ (add or "
                      "use a format there):\n" + "\n".join(uses))


def test_frame_file_check_sees_an_import(tmp_path, monkeypatch):
    probe = tmp_path / "probe.py"
    probe.write_text("from ..io.exr import read_exr\nfrom weathergen.io.images import to_uint8\n")
    monkeypatch.setitem(MODULES, "weathergen.render.probe", probe)
    assert _frame_file_uses("weathergen.render.probe") == ["line 1: read_exr"]


#: The two jobs over a dataset. What they share (a pair's particles and seeds, what its frames
#: show) lives in weathergen/jobs/, so that neither job imports the other.
JOBS = ("weathergen.render.job", "weathergen.attack.job")


def _job_imports(name: str) -> list[str]:
    """The imports in ``name`` of the other job of :data:`JOBS`, or of its package (which
    re-exports it)."""
    (other,) = (job for job in JOBS if job != name)
    return [f"line {line}: {target}" for target, line, _ in _imports(name)
            if target in (other, other.rpartition(".")[0])]


def test_the_render_and_attack_jobs_do_not_import_each_other():
    for job in JOBS:
        assert not _job_imports(job), (f"{job} imports the other job; move what they share to "
                                       f"weathergen/jobs/: {_job_imports(job)}")


def test_job_check_sees_an_import(tmp_path, monkeypatch):
    probe = tmp_path / "job.py"
    probe.write_text("from ..render.job import visibility_of\nfrom ..render import run_render\n"
                     "from ..jobs import pair_seed\n")
    monkeypatch.setitem(MODULES, "weathergen.attack.job", probe)
    assert _job_imports("weathergen.attack.job") == ["line 1: weathergen.render.job",
                                                     "line 2: weathergen.render"]
