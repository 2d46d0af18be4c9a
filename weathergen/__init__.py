"""weathergen: physically placed weather for optical-flow data, and weather attacks on flow networks."""

from __future__ import annotations

import importlib.abc
import importlib.util
import sys
from pathlib import Path

__version__ = "0.1.0"


class _CheckoutFolders(importlib.abc.MetaPathFinder):
    """Finds ``weathergen.cli`` and ``weathergen.presets`` in a source checkout's top-level folders.

    An install puts ``cli/`` and ``presets/`` inside the package (``package_dir`` in setup.cfg);
    in a source checkout they stay at the top level, beside ``weathergen/``. Python started in
    the checkout (a notebook there, ``python -c ...``) imports this package from the checkout, and
    this finder resolves the two subpackages (and so the preset files, the attack configurations
    and the command line) from the same checkout.
    """

    def __init__(self, folders: dict[str, Path]):
        self.folders = folders

    def find_spec(self, fullname, path=None, target=None):
        folder = self.folders.get(fullname)
        if folder is None:
            return None
        return importlib.util.spec_from_file_location(
            fullname, folder / "__init__.py", submodule_search_locations=[str(folder)])


def _checkout_folders() -> dict[str, Path]:
    """``{"weathergen.cli": ROOT/cli, ...}`` when this package is a source checkout's, else ``{}``."""
    package = Path(__file__).resolve().parent
    root = package.parent
    if not (root / "setup.cfg").is_file():
        return {}                       # an installed copy: the subpackages are inside it
    return {f"{__name__}.{name}": root / name for name in ("cli", "presets")
            if not (package / name).exists() and (root / name / "__init__.py").is_file()}


# First in line: an editable install of another checkout (its finder maps the same two names to
# its own folders) must not mix its command line or presets into this checkout's package.
if _checkout_folders():
    sys.meta_path.insert(0, _CheckoutFolders(_checkout_folders()))
