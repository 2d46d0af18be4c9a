"""``weathergen check``: validate a dataset tree and report what is missing or corrupt."""

from __future__ import annotations

import sys
from collections import defaultdict

import click
from rich.console import Console
from rich.table import Table

from weathergen.errors import DatasetError

from .options import dataset_options


@click.command()
@dataset_options
@click.option("--verbose", "-v", is_flag=True, help="List every faulty pair, not only the first per scene.")
def check(dataset, verbose):
    """Check that every selected frame pair can be read (frames, depth, cameras, flow).

    Prints one row per scene and exits with 0 only when every selected pair is readable.
    """
    console = Console()
    refs = dataset.pairs()
    if not refs:
        raise DatasetError(f"{dataset.root}: the selection holds no frame pairs")
    per_scene = defaultdict(list)
    for ref in refs:
        per_scene[ref.id.scene].append((ref, dataset.check(ref)))

    single_pass = dataset.name in ("kitti", "spring", "custom")   # one rendering, no pass to name
    where = dataset.selection.split if single_pass else f"{dataset.selection.split}/{dataset.selection.pass_}"
    table = Table(title=f"{dataset.name} {where} at {dataset.root}")
    for col, kw in (("scene", {}), ("pairs", {"justify": "right"}), ("readable", {"justify": "right"}),
                    ("depth scale", {"justify": "right"}), ("status", {})):
        table.add_column(col, **kw)
    bad_total = 0
    lines = []
    prefix = f"{dataset.root}/"   # paths relative to the root, which the title names
    for scene, results in per_scene.items():
        bad = [(r, msg) for r, msg in results if msg]
        bad_total += len(bad)
        shown = bad if verbose else bad[:1]
        lines += [f"{scene} frame {r.id.frame}: {msg.replace(prefix, '')}" for r, msg in shown]
        if len(bad) > len(shown):
            lines.append(f"{scene}: {len(bad) - len(shown)} more faulty pairs (--verbose lists all)")
        scale = getattr(dataset, "scale_of", lambda s: 1.0)(scene)
        status = f"[red]{len(bad)} faulty[/red]" if bad else "[green]ok[/green]"
        table.add_row(scene, str(len(results)), str(len(results) - len(bad)), f"{scale:g}", status)
    console.print(table)
    for line in lines:            # plain lines: long paths must not be folded mid-name
        click.echo(line)
    if bad_total:
        console.print(f"[red]{bad_total} of {len(refs)} pairs cannot be read.[/red]")
        sys.exit(1)
    pairs = f"{len(refs)} pair{'s' if len(refs) != 1 else ''}"
    scenes = f"{len(per_scene)} scene{'s' if len(per_scene) != 1 else ''}"
    console.print(f"[green]{'All ' if len(refs) > 1 else ''}{pairs} in {scenes} "
                  f"{'are' if len(refs) != 1 else 'is'} readable.[/green]")
