"""The engine's structure before and after a re-layout: modules, import edges and cycles,
between modules and between its parts (subpackages, and modules at its top), for the table of
docs/architecture.md.

    python scripts/engine_structure.py 74ebf29 main     # columns: those commits, then this tree

Counts come from the import graph of tests/test_imports.py (which also checks that the table's
last column is this tree's).
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tarfile
import tempfile
from io import BytesIO
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _graph_module():
    spec = importlib.util.spec_from_file_location("import_graph", ROOT / "tests" / "test_imports.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def figures_at(graph, revision: str | None) -> dict[str, int]:
    """The engine's figures at ``revision`` (a commit), or in this tree (None)."""
    if revision is None:
        return graph.structure(graph.MODULES)
    archive = subprocess.run(["git", "archive", revision, "weathergen"], cwd=ROOT, check=True,
                             capture_output=True).stdout
    with tempfile.TemporaryDirectory() as folder:
        with tarfile.open(fileobj=BytesIO(archive)) as tar:
            tar.extractall(folder, filter="data")
        return graph.structure(graph._modules({"weathergen": Path(folder) / "weathergen"}))


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("revisions", nargs="*", help="commits to compare with this tree")
    args = parser.parse_args(argv)
    graph = _graph_module()
    columns = [(rev, figures_at(graph, rev)) for rev in args.revisions]
    columns.append(("this tree", figures_at(graph, None)))
    print("| | " + " | ".join(name for name, _ in columns) + " |")
    print("|---|" + "---:|" * len(columns))
    for key in columns[-1][1]:
        print(f"| {key} | " + " | ".join(str(f[key]) for _, f in columns) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
