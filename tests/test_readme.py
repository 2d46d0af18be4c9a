"""README.md: short enough to read in five minutes, and its tour runs as written on the demo scene."""

from __future__ import annotations

import importlib.util
import re
import shlex
import subprocess
import sys

import pytest

from conftest import PROJECT_ROOT

README = (PROJECT_ROOT / "README.md").read_text()
#: The README's length limit in bytes: what it is, set-up, a tour, installing, links.
LIMIT = 15_000


def tour_commands() -> list[list[str]]:
    """The `weathergen` commands of the tour's bash block, continuation lines joined, comments cut."""
    section = README.split("## A five-minute tour", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    commands = []
    for line in block.replace("\\\n", " ").splitlines():
        words = shlex.split(line, comments=True)
        if words:
            assert words[0] == "weathergen", line
            commands.append(words[1:])
    return commands


def _quick_look() -> list[str]:
    (attack,) = [c for c in tour_commands() if c[0] == "attack"]
    return attack


def test_the_readme_is_short():
    size = len(README.encode())
    assert size <= LIMIT, f"README.md is {size} bytes; at most {LIMIT}: move details to docs/"


def test_the_tour_names_render_preview_attack_evaluate_and_the_shipped_checkpoint():
    names = [c[0] for c in tour_commands()]
    assert {"render", "preview", "presets", "attack", "evaluate"} <= set(names)
    attack = _quick_look()
    assert attack[attack.index("--checkpoint") + 1] == "raft-small"      # found by name
    assert "path/to" not in README


def test_make_bench_times_the_tour_and_the_quick_look_writes_a_folder_of_its_own():
    spec = importlib.util.spec_from_file_location("bench_quick_look",
                                                  PROJECT_ROOT / "speed" / "bench_quick_look.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.tour_commands(README) == tour_commands()      # make bench times the whole tour
    attack = _quick_look()
    out = attack[attack.index("--out") + 1]
    assert attack[:attack.index("--out")] + attack[attack.index("--out") + 2:] == bench.QUICK_LOOK
    # no other command of the README or docs writes there (the paper-scale attack has its own,
    # and attack's default, out/attack-snow, is the paper-scale example's)
    assert out != "out/attack-snow"
    for page in [PROJECT_ROOT / "README.md", *(PROJECT_ROOT / "docs").glob("*.md")]:
        for line in page.read_text().replace("\\\n", " ").splitlines():
            if f"--out {out}" in line or f"--weather {out}" in line:
                assert "--steps 20 --lr 1e-2" in line and "--model raft-small" in line, (page.name, line)


@pytest.mark.slow
def test_the_tour_runs_as_written(tmp_path):
    """Each command of the tour, in order, in a fresh folder, as a user types it: exit code 0 and
    the files it promises. The attack runs 2 of its 20 steps here (make bench runs it whole:
    speed/bench_quick_look.py)."""
    for words in tour_commands():
        if words[0] == "attack":
            assert words[words.index("--steps") + 1] == "20"
            words = [*words[:words.index("--steps") + 1], "2", *words[words.index("--steps") + 2:]]
        done = subprocess.run([sys.executable, "-m", "weathergen.cli", *words], cwd=tmp_path,
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"weathergen {shlex.join(words)}:\n{done.stderr[-2000:]}"
    out = tmp_path / "out"
    for path in ("snow/manifest.json", "snow/preview.png", "snow.gif", "street/manifest.json",
                 "street.mp4", "quick-look/summary.json"):
        assert (out / path).is_file(), path


def test_the_set_up_quotes_what_make_prints(tmp_path):
    """The lines the README says `make demo` and `make test` print on a fresh clone are theirs."""
    section = README.split("## Set up", 1)[1].split("\n## ", 1)[0]
    quoted = [q.removesuffix("...").removesuffix("...)").rstrip(" ;")
              for q in re.findall(r"`((?:installing|running) [^`]+)`", section)]
    assert len(quoted) >= 3, quoted
    venv = tmp_path / ".venv"
    printed = []
    for target in ("demo", "test"):
        plan = subprocess.run(["make", "-n", "-C", str(PROJECT_ROOT), target, f"VENV={venv}"],
                              check=True, capture_output=True, text=True).stdout
        printed += [m.replace(str(venv), ".venv") for m in re.findall(r'echo "([^"]+)"', plan)]
    for line in quoted:
        assert any(p.startswith(line) for p in printed), (line, printed)
