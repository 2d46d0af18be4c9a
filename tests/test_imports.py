"""The import structure: every import at the top of its module, and no import cycles.

Tools that follow imports (and readers) then see every dependency of a module in its first lines.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"weathergen": ROOT / "weathergen", "weathergen.cli": ROOT / "cli"}


def _modules(sources: dict[str, Path] = SOURCES) -> dict[str, Path]:
    out = {}
    for package, folder in sources.items():
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


def _is_package(name: str, modules: dict[str, Path] = MODULES) -> bool:
    return modules[name].name == "__init__.py"


def _import_stem(node: ast.ImportFrom, base: str) -> str:
    """The absolute module a ``from ... import`` statement reads from (``base``: the package the
    importing module sits in)."""
    if not node.level:
        return node.module or ""
    anchor = base.split(".")
    anchor = anchor[:len(anchor) - (node.level - 1)]
    return ".".join(anchor + ([node.module] if node.module else []))


def _imports(name: str, modules: dict[str, Path] = MODULES) -> list[tuple[str, int, bool]]:
    """(imported module, line, at module level) for every import of weathergen in ``name``."""
    tree = ast.parse(modules[name].read_text())
    top = {id(node) for node in tree.body}
    base = name if _is_package(name, modules) else name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            stem = _import_stem(node, base)
            targets = [stem]
            # "from .pkg import module" imports a module, not only a name
            targets += [f"{stem}.{a.name}" for a in node.names if f"{stem}.{a.name}" in modules]
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


def _graph(modules: dict[str, Path] = MODULES) -> dict[str, set[str]]:
    graph = {}
    for name in modules:
        edges = set()
        for target, _, _ in _imports(name, modules):
            # importing a.b.c runs a/__init__ and a/b/__init__ first, unless the importer is
            # inside them already
            parts = target.split(".")
            for i in range(1, len(parts) + 1):
                module = ".".join(parts[:i])
                if module in modules and module != name and not name.startswith(module + "."):
                    edges.add(module)
        graph[name] = edges
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[str]:
    """The import cycles a depth-first walk of ``graph`` meets (one per edge that closes one)."""
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
    return cycles


def structure(modules: dict[str, Path], package: str = "weathergen.engine") -> dict[str, int]:
    """Figures of the layout of ``package`` (docs/architecture.md compares them): its modules
    (its own ``__init__`` left out), the import edges between them and the cycles among them; its
    parts (a subpackage, or a module at its top) and the import edges and cycles between the
    parts; its modules over 600 lines. (No line counts: they would go stale with every edit.)"""
    inside = {n: p for n, p in modules.items() if n.startswith(package + ".")}
    graph = {n: {m for m in edges if m in inside} for n, edges in _graph(modules).items()
             if n in inside}
    depth = package.count(".") + 2
    parts: dict[str, set[str]] = {}
    for name, edges in graph.items():
        part = ".".join(name.split(".")[:depth])
        parts.setdefault(part, set()).update(
            {".".join(m.split(".")[:depth]) for m in edges} - {part})
    lines = [len(p.read_text().splitlines()) for p in inside.values()]
    return {"modules": len(inside),
            "import edges": sum(map(len, graph.values())), "cycles": len(_cycles(graph)),
            "parts": len(parts), "edges between parts": sum(map(len, parts.values())),
            "cycles between parts": len(_cycles(parts)),
            "modules over 600 lines": sum(n > 600 for n in lines)}


def test_the_engine_figures_in_the_docs_are_the_trees():
    """docs/architecture.md's "after" column is this tree's engine (scripts/engine_structure.py
    writes the table)."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    rows = {line.split("|")[1].strip(): line.split("|")[-2].strip()
            for line in map(str.strip, text.splitlines())
            if line.startswith("| ") and line.count("|") == 5}
    figures = structure(MODULES)
    shown = {key: rows.get(key) for key in figures}
    assert shown == {key: str(value) for key, value in figures.items()}, \
        "docs/architecture.md's engine figures differ: run scripts/engine_structure.py"


def test_there_is_no_import_cycle():
    cycles = _cycles(_graph())
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


#: The floors of weathergen/engine/ (docs/architecture.md), lowest first: a part (a subpackage or
#: a module at the engine's top) imports only lower floors, so sampling and rendering do not
#: import each other.
ENGINE_FLOORS = [("weathergen.engine.common", "weathergen.engine.weather"),
                 ("weathergen.engine.records", "weathergen.engine.views"),
                 ("weathergen.engine.sampling", "weathergen.engine.rendering"),
                 ("weathergen.engine.pipeline",)]


def _engine_part(module: str) -> str:
    return ".".join(module.split(".")[:3])


def _engine_upward() -> list[str]:
    rank = {part: i for i, floor in enumerate(ENGINE_FLOORS) for part in floor}
    graph = _graph()
    engine = [name for name in MODULES if name.startswith("weathergen.engine.")]
    assert {_engine_part(name) for name in engine} == set(rank), "a subpackage has no floor"
    return [f"{a} imports {b}" for a in engine for b in graph[a]
            if b.startswith("weathergen.engine.") and _engine_part(a) != _engine_part(b)
            and rank[_engine_part(a)] <= rank[_engine_part(b)]]


def test_each_engine_floor_imports_only_the_floors_below_it():
    upward = _engine_upward()
    assert not upward, "engine imports that do not go down a floor:\n" + "\n".join(upward)


def test_engine_floor_check_sees_sampling_import_rendering(tmp_path, monkeypatch):
    probe = tmp_path / "probe.py"
    probe.write_text("from ..rendering.tracks import Tracks\nfrom ..views import View\n")
    monkeypatch.setitem(MODULES, "weathergen.engine.sampling.probe", probe)
    assert sorted(_engine_upward()) == ["weathergen.engine.sampling.probe imports "
                                        "weathergen.engine.rendering",
                                        "weathergen.engine.sampling.probe imports "
                                        "weathergen.engine.rendering.tracks"]


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
    probe.write_text("from .engine.rendering.renderer import _hidden\nfrom .engine import sampling\n"
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


#: The blend module: every way weather is blended into frames (a single record's blend modes,
#: combined weather's layers in depth order) is written there, with its backward pass.
BLEND_OWNER = "weathergen.engine.rendering.composite"
#: The engine's other custom autograd functions, none of which blends: the splat's scatter, the
#: crop and the upsampling of its sums.
OTHER_AUTOGRAD = {"weathergen.engine.rendering.splat": {"_Splat"},
                  "weathergen.engine.rendering.planes": {"_Crop", "_Upsample"}}


def _autograd_functions(name: str) -> set[str]:
    """The classes of module ``name`` derived from ``torch.autograd.Function``."""
    tree = ast.parse(MODULES[name].read_text())
    return {node.name for node in ast.walk(tree) if isinstance(node, ast.ClassDef)
            and any(ast.unparse(base).split(".")[-1] == "Function" for base in node.bases)}


def _complement(node: ast.AST, names: set[str]) -> bool:
    """Whether ``node`` is ``1 − x`` (a transmission), a name bound to one, an element or a
    slice of one, or one clamped."""
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub):
        return isinstance(node.left, ast.Constant) and node.left.value == 1
    if isinstance(node, ast.Name):
        return node.id in names
    if isinstance(node, ast.Subscript):
        return _complement(node.value, names)
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
            and node.func.attr in ("clamp", "clamp_"):
        return _complement(node.func.value, names)
    return False


def _complement_names(function: ast.AST) -> set[str]:
    """The names a function binds to complements (``keep = 1 − A``; ``a, b = 1 − x, 1 − y``;
    ``keep = [1 − c for c in cover]``), to a fixed point."""
    names: set[str] = set()
    pairs = []
    for node in ast.walk(function):
        if isinstance(node, ast.Assign):
            for target in node.targets:
                if isinstance(target, ast.Tuple) and isinstance(node.value, ast.Tuple):
                    pairs += zip(target.elts, node.value.elts)
                else:
                    pairs.append((target, node.value))
    while True:
        found = {target.id for target, value in pairs if isinstance(target, ast.Name)
                 and (_complement(value, names) or isinstance(value, ast.ListComp)
                      and _complement(value.elt, names))}
        if found <= names:
            return names
        names |= found


def _unwrapped(node: ast.AST) -> ast.AST:
    """``node`` without its subscripts, clamps and conversions (``(1 - w)[:, None]`` ->
    ``1 - w``, ``(x * y).to(dtype)`` -> ``x * y``)."""
    while isinstance(node, ast.Subscript) or isinstance(node, ast.Call) \
            and isinstance(node.func, ast.Attribute) and node.func.attr in ("clamp", "clamp_",
                                                                             "to"):
        node = node.value if isinstance(node, ast.Subscript) else node.func.value
    return node


def _weighted_terms(function: ast.AST, names: set[str]) -> dict[str, ast.AST]:
    """The names a function binds to a product with a complement (``light = ((1 − t) A)``)."""
    return {node.targets[0].id: _unwrapped(node.value) for node in ast.walk(function)
            if isinstance(node, ast.Assign) and len(node.targets) == 1
            and isinstance(node.targets[0], ast.Name)
            and isinstance(_unwrapped(node.value), ast.BinOp)
            and isinstance(_unwrapped(node.value).op, ast.Mult)
            and any(_complement(f, names) for f in (_unwrapped(node.value).left,
                                                    _unwrapped(node.value).right))}


def _over(term: ast.AST, other: ast.AST, names: set[str], weighted: dict) -> str:
    """What ``term + other`` is: ``"over"`` for ``x (1 − a) + c`` (``term`` a product with a
    complement, or a name bound to one, ``other`` not weighted by that complement's ``a``),
    ``"lerp"`` for ``x (1 − w) + y w`` (an interpolation), else ``""``."""
    term = weighted.get(term.id, term) if isinstance(term, ast.Name) else _unwrapped(term)
    if not (isinstance(term, ast.BinOp) and isinstance(term.op, ast.Mult)):
        return ""
    weights = [_unwrapped(f) for f in (term.left, term.right) if _complement(f, names)]
    if not weights:
        return ""
    inner = {ast.unparse(w.right) for w in weights if isinstance(w, ast.BinOp)}
    weighted = isinstance(other, ast.BinOp) and isinstance(other.op, ast.Mult) \
        and {ast.unparse(_unwrapped(f)) for f in (other.left, other.right)} & inner
    return "lerp" if weighted else "over"


def _formula(node: ast.AST, names: set[str], weighted: dict) -> str:
    """``"over"``, ``"lerp"`` (an interpolation: ``torch.lerp``, ``x.lerp`` or written out) or
    ``""`` for one node of a function whose complement names are ``names`` and whose names bound
    to weighted terms are ``weighted``."""
    if isinstance(node, ast.Call):
        func = node.func
        attr = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
        if attr in ("lerp", "lerp_"):
            return "lerp"
        torch_call = isinstance(func, ast.Attribute) and ast.unparse(func.value) == "torch"
        factors = node.args[1:] if torch_call else node.args
        return "over" if attr in ("addcmul", "addcmul_") \
            and any(_complement(a, names) for a in factors) else ""
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        kinds = {_over(side, other, names, weighted) for side, other in
                 ((node.left, node.right), (node.right, node.left))}
        return "over" if "over" in kinds else "lerp" if "lerp" in kinds else ""
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub) \
            and isinstance(node.left, ast.Constant) and node.left.value == 1 \
            and isinstance(node.right, ast.BinOp) and isinstance(node.right.op, ast.Mult) \
            and any(_complement(_unwrapped(f), names) for f in (node.right.left, node.right.right)):
        return "over"               # an opacity over another: 1 − t (1 − α)
    return ""


#: The functions that interpolate samples (bilinear reads and weights, a template's upsampling):
#: outside the blend module, any other interpolation is a blend (the scene seen through the
#: air, ``J t + A (1 − t)``, is one).
RESAMPLERS = {"weathergen.engine.rendering.splat": {"_Blocks.__init__", "_Splat.backward"},
              "weathergen.engine.rendering.transmittance": {"Air._lookup"},
              "weathergen.engine.rendering.combined": {"_read_sums"},
              "weathergen.engine.weather.templates": {"_smooth_noise"}}


def _blend_formulas(name: str) -> list[str]:
    """Where module ``name`` writes a blend: a sum with a term weighted by a complement,
    ``I (1 − A) + C`` written as ``x * (1 - a) + c`` or ``torch.addcmul(c, x, keep)`` (also the
    layers' opacity ``1 − (1 − a)(1 − b)`` as an ``addcmul`` of two complements, or an opacity
    over another ``1 − t (1 − α)``), or an interpolation ``x (1 − w) + y w`` (``torch.lerp``; the
    fog ``J t + A (1 − t)``) outside the functions :data:`RESAMPLERS` names."""
    tree = ast.parse(MODULES[name].read_text())
    defined = [(f"{c.name}.{f.name}", f) for c in tree.body if isinstance(c, ast.ClassDef)
               for f in c.body if isinstance(f, ast.FunctionDef)] \
        + [(f.name, f) for f in tree.body if isinstance(f, ast.FunctionDef)]
    resampling = {id(node) for qualname, function in defined
                  if qualname in RESAMPLERS.get(name, ()) for node in ast.walk(function)}
    found = []
    for function in ast.walk(tree):
        if not isinstance(function, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        names = _complement_names(function)
        weighted = _weighted_terms(function, names)
        for node in ast.walk(function):
            kind = _formula(node, names, weighted)
            if kind == "over" or kind == "lerp" and id(node) not in resampling:
                found.append((node.lineno, ast.unparse(node)))
    return [f"line {line}: {text}" for line, text in sorted(set(found))]


def test_blend_modes_and_layer_compositing_have_one_owner():
    """The blend module alone defines the autograd functions that blend weather into frames and
    writes the blend formulas; the engine's other modules call it (docs/architecture.md)."""
    engine = [name for name in MODULES if name.startswith("weathergen.engine.")]
    stray = [f"{MODULES[name].relative_to(ROOT)} defines {cls}" for name in engine
             if name != BLEND_OWNER
             for cls in sorted(_autograd_functions(name) - OTHER_AUTOGRAD.get(name, set()))]
    stray += [f"{MODULES[name].relative_to(ROOT)} {use}" for name in engine
              if name != BLEND_OWNER for use in _blend_formulas(name)]
    assert not stray, (f"weather blended into frames outside {BLEND_OWNER} (move it there):\n"
                       + "\n".join(stray))
    # the check sees the owner's own: the single-record blend, the closed forms, the network
    assert {"_Blend", "_TwoLayers", "_LayeredBlend"} <= _autograd_functions(BLEND_OWNER)
    assert len(_blend_formulas(BLEND_OWNER)) >= 5, _blend_formulas(BLEND_OWNER)
    # ... and the air's: the fog, the opacity over the air's, the particles' tint
    owned = "\n".join(_blend_formulas(BLEND_OWNER))
    for formula in ("torch.lerp(airlight, image, transmission)",
                    "1 - transmission * (1 - opacity)", "colour * passed[:, None] + light"):
        assert formula in owned, owned


def test_blend_check_sees_a_blend_outside_its_module(tmp_path, monkeypatch):
    probe = tmp_path / "probe.py"
    probe.write_text(
        "import torch\n"
        "class _Over(torch.autograd.Function):\n    pass\n"
        "def over(image, alpha, colour):\n    return image * (1 - alpha) + colour\n"
        "def kept(image, alpha, colour):\n    keep = 1 - alpha\n"
        "    return torch.addcmul(colour, image, keep)\n"
        "def layers(image, cover, paint):\n    keep = [1 - c for c in cover]\n"
        "    return torch.addcmul(paint[0], image, keep[0])\n"
        "def opacity(one, a, b):\n    clear_a, clear_b = 1 - a.clamp(0, 1), 1 - b.clamp(0, 1)\n"
        "    return torch.addcmul(one, clear_a, clear_b, value=-1)\n"
        "def not_a_blend(x, y, w):\n    return torch.addcmul(1 - x, y, w) + (1 - x) - y * w\n"
        "def lerp(x, y, w):\n    return x * (1 - w)[:, None] + y * w[:, None]\n"
        "def fog(image, t, airlight):\n    return image * t + airlight * (1 - t)\n"
        "def fog2(image, t, airlight):\n    return torch.lerp(airlight, image, t)\n"
        "def opacity2(alpha, t):\n    return 1 - t * (1 - alpha)\n"
        "def tint(colour, t, airlight):\n    light = ((1 - t)[:, None] * airlight).to(colour.dtype)\n"
        "    return colour * t[:, None] + light\n")
    monkeypatch.setitem(MODULES, "weathergen.engine.probe", probe)
    monkeypatch.setitem(RESAMPLERS, "weathergen.engine.probe", {"lerp"})
    assert _autograd_functions("weathergen.engine.probe") == {"_Over"}
    assert [use.split(":")[0] for use in _blend_formulas("weathergen.engine.probe")] == \
        ["line 5", "line 8", "line 11", "line 14", "line 20", "line 22", "line 24", "line 27"]
