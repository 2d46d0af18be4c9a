"""``weathergen demo-scene OUT``: write the bundled demo scene to a folder."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import click

from weathergen.datasets.demo import write_demo_scene
from weathergen.errors import ConfigError
from weathergen.io.atomic import UMASK

from .options import BAD_INPUT, STOPPED, exit_codes, overwrite_option


@click.command("demo-scene", epilog=exit_codes(("0", "the scene written"), BAD_INPUT, STOPPED))
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@overwrite_option("Replace OUT if it exists and is not empty.")
def demo_scene(out: Path, overwrite: bool):
    """Write the bundled demo scene (Sintel layout, with depth, cameras and exact flow) to OUT."""
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise ConfigError(f"{out}: folder is not empty (use --overwrite to replace it)")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    except OSError as exc:
        raise ConfigError(f"{out.parent}: cannot write here ({exc.strerror})") from None
    try:
        tmp.chmod(0o777 & ~UMASK)     # a plain folder, not the owner-only temporary one
        write_demo_scene(tmp)
        if out.exists():
            shutil.rmtree(out)
        os.rename(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    click.echo(f"Demo scene written to {out} (read it with --dataset sintel --root {out}).")
