"""The figures file (docs/figures/bench.json and bench.md): every speed and memory figure of the
docs, written by `make bench` through speed/figures.py with the tree and machine it was
measured on; the docs cite it instead of repeating figures."""

from __future__ import annotations

import importlib.util
import json
import re
import shlex

import pytest

from conftest import PROJECT_ROOT

FIGURES = PROJECT_ROOT / "docs" / "figures" / "bench.json"


def _helper():
    spec = importlib.util.spec_from_file_location("figures", PROJECT_ROOT / "speed" / "figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_run_is_recorded_with_its_tree_machine_and_output_and_a_rerun_replaces_it(
        tmp_path, monkeypatch, capsys):
    figures = _helper()
    path = tmp_path / "bench.json"
    monkeypatch.setenv("BENCH_FIGURES", str(path))
    monkeypatch.setenv("BENCH_CLOCK", "cpu")

    def main(text):
        def run():
            print(text)
        return run

    assert figures.record(main("snow 0.1 s"), ["speed/bench.py"]) is None
    assert figures.record(main("pair 0.2 s"), ["x/bench_field.py", "--frames", "20"]) is None
    assert "snow 0.1 s" in capsys.readouterr().out          # printed as before
    data = json.loads(path.read_text())
    assert list(data["sections"]) == ["python speed/bench.py",
                                      "python speed/bench_field.py --frames 20"]
    section = data["sections"]["python speed/bench.py"]
    assert section["output"] == "snow 0.1 s\n"
    assert re.fullmatch(r"[0-9a-f]{40}", section["commit"]) and isinstance(section["dirty"], bool)
    assert section["machine"]["cores"] >= 1 and section["machine"]["cpu"]
    assert section["machine"]["torch"] and section["settings"] == {"BENCH_CLOCK": "cpu"}
    # a rerun of one command replaces its section and keeps the others, in make bench's order
    figures.record(main("snow 0.3 s"), ["speed/bench.py"])
    data = json.loads(path.read_text())
    assert data["sections"]["python speed/bench.py"]["output"] == "snow 0.3 s\n"
    assert len(data["sections"]) == 2
    page = path.with_suffix(".md").read_text()
    assert page == figures.markdown(data) and "snow 0.3 s" in page and "snow 0.1 s" not in page
    assert f"`{section['commit'][:12]}`" in page


def test_failed_runs_and_worker_runs_are_not_recorded(tmp_path, monkeypatch):
    figures = _helper()
    path = tmp_path / "bench.json"
    monkeypatch.setenv("BENCH_FIGURES", str(path))
    assert figures.record(lambda: print("half") or 1, ["speed/bench_models.py"]) == 1
    assert figures.record(lambda: print("{}"), ["speed/bench_core.py", "--worker"]) is None
    assert figures.record(lambda: print("{}"), ["speed/bench_attack.py", "--one", "x"]) is None
    assert not path.exists()
    monkeypatch.setenv("BENCH_FIGURES", "none")
    figures.record(lambda: print("x"), ["speed/bench.py"])
    assert not path.exists()


def _make_bench_scripts() -> list[str]:
    """The scripts `make bench` runs on every machine (the CUDA-only line aside)."""
    makefile = (PROJECT_ROOT / "Makefile").read_text()
    recipe = makefile.split("\nbench:", 1)[1].split("\n\n", 1)[0]
    lines = [line for line in recipe.splitlines() if "cuda" not in line and "--device" not in line]
    return sorted({m for line in lines for m in re.findall(r"speed/(\w+\.py)", line)})


def test_the_figures_file_holds_every_make_bench_command_with_its_tree_and_machine():
    figures = _helper()
    data = json.loads(FIGURES.read_text())
    scripts = {shlex.split(c)[1].rsplit("/", 1)[-1] for c in data["sections"]}
    expected = _make_bench_scripts()
    assert len(expected) >= 10 and "bench_quick_look.py" in expected
    assert set(expected) <= scripts, f"make bench writes no figures yet for {set(expected) - scripts}"
    for command, section in data["sections"].items():
        assert re.fullmatch(r"[0-9a-f]{40}", section["commit"]), command
        assert section["machine"]["cpu"] and section["machine"]["cores"] and section["machine"]["torch"]
        assert section["output"].strip(), command
    # the page is the JSON, rendered: nobody edits the figures by hand
    assert FIGURES.with_suffix(".md").read_text() == figures.markdown(data)


@pytest.mark.parametrize("page", ["README.md", "docs/engine.md", "docs/attack.md", "docs/models.md",
                                  "docs/training.md", "docs/scale.md"])
def test_the_docs_cite_the_figures_file(page):
    text = (PROJECT_ROOT / page).read_text()
    assert "figures/bench.md" in text or "figures/gpu.md" in text, page
