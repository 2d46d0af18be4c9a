"""``weathergen inspect FILE`` and ``weathergen preview DIR``: look at what a render wrote."""

from __future__ import annotations

import json
from pathlib import Path

import click
from rich.console import Console
from rich.table import Table

from weathergen.engine.particles import TENSOR_FIELDS, Particles, stored_as
from weathergen.io.atomic import write_error
from weathergen.io.images import write_png
from weathergen.outputs import read_metadata
from weathergen.render import contact_sheet


def _preset_origin(name: str, source: str) -> str:
    """A bundled preset by its name; a user's preset file by name and path."""
    return name if not source or source.startswith("preset ") else f"{name} (from {source})"


@click.command()
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
def inspect(file: Path):
    """Show what a particle-metadata file holds: pair, seed, preset, counts and value ranges."""
    arrays = read_metadata(file)
    console = Console()
    n = int(arrays["position"].shape[0]) if "position" in arrays else 0
    preset = json.loads(str(arrays["preset"])) if "preset" in arrays else {}
    head = Table(title=str(file), show_header=False)
    head.add_column("key")
    head.add_column("value")
    rows = [
        ("pair", f"{arrays['pair_dataset']}/{arrays['pair_split']}/{arrays['pair_scene']} "
                 f"frame {int(arrays['pair_frame'])}"),
        ("seed", str(int(arrays["seed"]))),
        ("preset", _preset_origin(str(arrays["preset_name"]), preset.get("source", ""))),
        ("particles", str(n)),
        ("visible in frame 1 / 2", f"{int(arrays.get('visible1', -1))} / {int(arrays.get('visible2', -1))}"),
        ("reference frame", str(arrays.get("frame", "?"))),
        ("blend", str(arrays.get("blend", "?"))),
        ("motion blur", f"length {float(arrays.get('blur_length', 0)):g}, "
                        f"{int(arrays.get('blur_samples', 1))} samples"),
        ("templates", str(arrays.get("templates", "?"))),
        ("format", f"metadata v{int(arrays['metadata_version'])}, particles v{int(arrays.get('format_version', 0))}, "
                   f"written by weathergen {arrays.get('weathergen_version', '?')}"),
        ("file size", f"{file.stat().st_size:,} bytes"),
    ]
    for k, v in rows:
        head.add_row(k, v)
    console.print(head)
    # What Particles.load gives (codes decoded), with how the file stores it beside
    particles = Particles.load(file)
    ranges = Table(title="per-particle values (as Particles.load reads them)")
    for col in ("field", "dtype", "shape", "min", "max", "mean", "stored as"):
        ranges.add_column(col, justify="right" if col in ("min", "max", "mean") else "left",
                          no_wrap=True)
    for name in TENSOR_FIELDS:
        t = getattr(particles, name)
        if t.numel():
            f = t.double()
            stats = (f"{f.min().item():.4g}", f"{f.max().item():.4g}", f"{f.mean().item():.4g}")
        else:
            stats = ("-", "-", "-")
        ranges.add_row(name, str(t.dtype).removeprefix("torch."), "×".join(map(str, t.shape)), *stats,
                       stored_as(arrays, name))
    console.print(ranges)


@click.command()
@click.argument("render_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="PNG to write. Default: RENDER_DIR/preview.png.")
@click.option("--pairs", type=click.IntRange(min=1), default=4, show_default=True,
              help="Pairs to show (the first ones); the sheet says when there are more.")
@click.option("--width", type=click.IntRange(min=64), default=480, show_default=True,
              help="Width of each tile.")
def preview(render_dir: Path, out, pairs, width):
    """Write a contact sheet of a render output: original, weather frame and particle opacity."""
    sheet = contact_sheet(render_dir, pairs=pairs, width=width)
    out = out or render_dir / "preview.png"
    try:
        write_png(out, sheet.image)
    except OSError as exc:
        raise write_error(exc, out, "pass --out PATH.png to write it elsewhere") from None
    if sheet.partial:
        click.echo(f"Preview of {sheet.shown} of {sheet.total} pairs written to {out} "
                   f"(--pairs {sheet.total} shows all)")
    else:
        click.echo(f"Preview of {sheet.total} pair{'s' if sheet.total != 1 else ''} written to {out}")
