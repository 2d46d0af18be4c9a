"""A source checkout is a package: Python started in the repository root imports the checkout's
weathergen with its presets, attack configurations, templates and command line, as an install does.

Each check runs a bare interpreter (``python -S``: no ``.pth`` file runs, so the editable install's
finder is absent) that reaches the dependencies through ``PYTHONPATH`` alone, as a checkout with
its dependencies installed but the package not installed.
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

from conftest import PROJECT_ROOT

# What a user of either layout does first; every path printed must lie under the expected folder.
PROBE = """
import sys
import weathergen, weathergen.cli.main, weathergen.presets
from weathergen.attack.configs import attack_config
from weathergen.engine import load_preset
from weathergen.engine.weather.templates import load_templates
assert load_preset("snow").count == 3000 and load_preset("snow-light").model == "field"
assert attack_config("snow").preset == "snow"
assert load_templates("flakes").count == 8
import os, tempfile
os.environ["WEATHERGEN_CACHE"] = tempfile.mkdtemp()       # an empty cache: the name finds the shipped file
from weathergen.models import checkpoint_spec
from weathergen.models.checkpoints import resolve_named, sha256_of
weights = resolve_named(checkpoint_spec("raft-small"))
assert sha256_of(weights) == checkpoint_spec("raft-small").sha256
for module in (weathergen, weathergen.cli.main, weathergen.presets):
    print(module.__file__)
print(weights)
"""


#: The released RAFT-small weights, package data found by the name ``raft-small``.
WEIGHTS = Path("weathergen", "models", "weights", "raft-small.pth")


def _bare(code: str, cwd: Path, path: list[str]) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}
    env["PYTHONPATH"] = os.pathsep.join(path)
    return subprocess.run([sys.executable, "-S", *code], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def _dependencies() -> list[str]:
    return site.getsitepackages()


def test_python_in_the_repository_root_imports_the_checkout_with_presets_and_cli():
    res = _bare(["-c", PROBE], PROJECT_ROOT, _dependencies())
    assert res.returncode == 0, res.stderr
    files = [Path(line) for line in res.stdout.split()]
    assert files == [PROJECT_ROOT / "weathergen" / "__init__.py", PROJECT_ROOT / "cli" / "main.py",
                     PROJECT_ROOT / "presets" / "__init__.py", PROJECT_ROOT / WEIGHTS]


def test_the_command_line_runs_from_the_repository_root_as_a_module():
    res = _bare(["-m", "weathergen.cli", "presets", "snow"], PROJECT_ROOT, _dependencies())
    assert res.returncode == 0, res.stderr
    assert "count" in res.stdout and "3000" in res.stdout


def test_the_package_runs_the_command_line_as_a_module():
    """``python -m weathergen`` is ``python -m weathergen.cli``: the commands, their exit codes."""
    res = _bare(["-m", "weathergen", "presets", "snow"], PROJECT_ROOT, _dependencies())
    assert res.returncode == 0, res.stderr
    assert "count" in res.stdout and "3000" in res.stdout
    bad = _bare(["-m", "weathergen", "presets", "no-such-preset"], PROJECT_ROOT, _dependencies())
    assert bad.returncode == 2 and bad.stderr.startswith("Error:") and "Traceback" not in bad.stderr
    usage = _bare(["-m", "weathergen", "--help"], PROJECT_ROOT, _dependencies())
    assert usage.returncode == 0, usage.stderr
    assert usage.stdout.startswith("Usage: weathergen ") and "models" in usage.stdout


# setuptools' editable finder, as `pip install -e` of another checkout installs it: appended to
# sys.meta_path at start-up, mapping the package and its two relocated subpackages by name.
OTHER_EDITABLE = """
import sys
from importlib.util import spec_from_file_location
from pathlib import Path
OTHER = Path(sys.argv[1])
class Editable:
    @classmethod
    def find_spec(cls, fullname, path=None, target=None):
        if fullname in ("weathergen", "weathergen.cli", "weathergen.presets"):
            folder = OTHER / {"weathergen": "weathergen", "weathergen.cli": "cli",
                              "weathergen.presets": "presets"}[fullname]
            return spec_from_file_location(fullname, folder / "__init__.py",
                                           submodule_search_locations=[str(folder)])
        return None
sys.meta_path.append(Editable)
"""


def test_an_editable_install_of_another_checkout_does_not_mix_into_this_one(tmp_path):
    """Python in this root with another checkout installed editable: all three come from here."""
    other = tmp_path / "other"
    for name in ("weathergen", "cli", "presets"):
        (other / name).mkdir(parents=True)
        (other / name / "__init__.py").write_text("raise ImportError('the other checkout')\n")
    res = _bare(["-c", OTHER_EDITABLE + PROBE, str(other)], PROJECT_ROOT, _dependencies())
    assert res.returncode == 0, res.stderr
    files = [Path(line) for line in res.stdout.split()]
    assert files == [PROJECT_ROOT / "weathergen" / "__init__.py", PROJECT_ROOT / "cli" / "main.py",
                     PROJECT_ROOT / "presets" / "__init__.py", PROJECT_ROOT / WEIGHTS]


def test_an_installed_wheel_carries_presets_cli_templates_and_weights(tmp_path):
    """The non-editable install (what `make install` does) still finds everything inside itself."""
    source = tmp_path / "source"
    source.mkdir()
    for name in ("setup.cfg", "pyproject.toml", "README.md"):
        shutil.copy(PROJECT_ROOT / name, source / name)
    for name in ("weathergen", "cli", "presets"):
        shutil.copytree(PROJECT_ROOT / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
    wheels, target = tmp_path / "wheels", tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                    "-w", str(wheels), str(source)], check=True, capture_output=True, timeout=300)
    wheel = next(wheels.glob("weathergen-*.whl"))
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target),
                    str(wheel)], check=True, capture_output=True, timeout=300)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    res = _bare(["-c", PROBE], elsewhere, [str(target), *_dependencies()])
    assert res.returncode == 0, res.stderr
    files = [Path(line) for line in res.stdout.split()]
    assert files == [target / "weathergen" / "__init__.py", target / "weathergen" / "cli" / "main.py",
                     target / "weathergen" / "presets" / "__init__.py", target / WEIGHTS]
