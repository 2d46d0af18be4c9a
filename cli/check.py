"""``weathergen check``: validate a dataset tree and report what is missing or corrupt."""

from __future__ import annotations

import sys

import click
from rich.console import Console
from rich.table import Table

from weathergen.datasets.checking import check_dataset, relative
from weathergen.errors import DatasetError
from weathergen.words import counted

from .options import STOPPED, dataset_options, exit_codes


@click.command(epilog=exit_codes(
    ("0", "every selected pair can be read (warnings may be printed)"),
    ("1", "some selected pairs cannot be read (each named)"),
    ("2", "bad options, or a root that is not of the chosen layout"), STOPPED))
@dataset_options
@click.option("--geometry", is_flag=True,
              help="Also measure how well depth and cameras reproduce the dataset's ground-truth "
                   "flow on static pixels seen in both frames (median, 90th percentile, share "
                   "within 1 px); without ground-truth flow, how well they map frame 2 onto "
                   "frame 1 (grey-level error against leaving frame 2 in place).")
@click.option("--geometry-pairs", type=click.IntRange(min=1), default=3, show_default=True,
              help="With --geometry: pairs per scene compared (spread over the scene).")
@click.option("--verbose", "-v", is_flag=True, help="List every file of a problem, not only the first few.")
def check(dataset, geometry, geometry_pairs, verbose):
    """Check that every selected frame pair can be read (frames, depth, cameras, flow).

    Prints one row per scene, then every problem of each scene grouped by kind, and exits with 0
    only when every selected pair is readable (warnings do not fail).
    """
    console = Console()
    scenes = check_dataset(dataset, geometry=geometry, geometry_pairs=geometry_pairs)
    if not scenes:
        raise DatasetError(dataset.no_pairs_message())

    where = (dataset.selection.split if dataset.single_pass      # one rendering, no pass to name
             else f"{dataset.selection.split}/{dataset.selection.pass_}")
    table = Table(title=f"{dataset.name} {where} at {dataset.root}")
    columns = [("scene", {}), ("pairs", {"justify": "right"}), ("readable", {"justify": "right"}),
               ("depth scale", {"justify": "right"}), ("status", {})]
    if geometry:
        columns += [("flow err median", {"justify": "right"}), ("p90", {"justify": "right"}),
                    ("≤1 px", {"justify": "right"})]
    for col, kw in columns:
        table.add_column(col, **kw)
    lines = []
    shown_max = None if verbose else 3
    for sc in scenes:
        readable = len(sc.pairs) - sc.faulty
        groups = sc.grouped()
        errors = sum(1 for sev, _, _ in groups if sev == "error")
        warnings = len(groups) - errors
        if sc.ok:
            status = "[green]ok[/green]" + (f" [yellow]({counted(warnings, 'warning')})[/yellow]"
                                            if warnings else "")
        else:
            status = f"[red]{sc.faulty} faulty[/red]" if sc.pairs else "[red]no pairs[/red]"
        row = [sc.scene, str(len(sc.pairs)), str(readable), f"{sc.depth_scale:g}", status]
        if geometry:
            g = sc.geometry
            row += (["-", "-", "-"] if g is None or not g.pixels else
                    [f"{g.median_px:.3f}", f"{g.p90_px:.3f}", f"{100 * g.within_1px:.1f}%"])
        table.add_row(*row)
        lines += _scene_lines(sc, groups, geometry, dataset.root, shown_max)
    console.print(table)
    for line in lines:            # plain lines: long paths must not be folded mid-name
        click.echo(line)
    total = sum(len(sc.pairs) for sc in scenes)
    bad_total = sum(sc.faulty for sc in scenes)
    if bad_total or not all(sc.ok for sc in scenes):
        unpaired = [sc.scene for sc in scenes if not sc.pairs]
        msg = f"{bad_total} of {counted(total, 'pair')} cannot be read."
        if unpaired:
            msg += f" {counted(len(unpaired), 'scene')} without pairs: {', '.join(unpaired)}."
        console.print(f"[red]{msg}[/red]")
        sys.exit(1)
    console.print(f"[green]{'All ' if total > 1 else ''}{counted(total, 'pair')} in "
                  f"{counted(len(scenes), 'scene')} "
                  f"{'are' if total != 1 else 'is'} readable.[/green]")


def _scene_lines(sc, groups, geometry: bool, root, shown_max) -> list[str]:
    """The lines under the table for one scene: its pairs' notes, its geometry, its problems
    (``groups``, each listing at most ``shown_max`` places)."""
    lines = [f"{sc.scene} frame {pc.ref.id.frame}: {note}" for pc in sc.pairs for note in pc.notes]
    if geometry and sc.pairs:
        g = sc.geometry
        lines.append(f"{sc.scene}: geometry: " + (
            _photometric_line(sc.photometric) if g is None else
            "no pixel to compare (none static, measured and seen in both frames)" if not g.pixels
            else f"flow error median {g.median_px:.3f} px, p90 {g.p90_px:.3f} px, "
                 f"{100 * g.within_1px:.1f}% within 1 px ({counted(g.pairs, 'pair')}, "
                 f"{g.pixels} pixels)"))
    for sev, kind, places in groups:
        places = [relative(p, root) for p in places]
        listed = places if shown_max is None else places[:shown_max]
        more = f" and {len(places) - len(listed)} more (--verbose lists all)" if len(places) > len(listed) else ""
        at = f": {', '.join(listed)}{more}" if places else ""
        lines.append(f"{sc.scene}: {'warning: ' if sev == 'warning' else ''}{kind}{at}")
    return lines


def _photometric_line(p) -> str:
    """The geometry line of a scene without ground-truth flow (the photometric check)."""
    if p is None:
        return "no ground-truth flow to compare with"
    if not p.pixels:
        return "no ground-truth flow, and no pixel to compare the frames on (none measured and seen in both)"
    figures = (f"frame 2 moved by depth and cameras differs from frame 1 by {p.error:.4f} (mean grey "
               f"level), left in place by {p.unmoved_error:.4f}; median motion {p.motion_px:.2f} px "
               f"({counted(p.pairs, 'pair')}, {100 * p.coverage:.0f}% of the pixels)")
    if not p.judged:
        verdict = "too little motion to judge"
    elif p.explained:
        verdict = "consistent"
    else:
        verdict = "NOT consistent"
    return f"no ground-truth flow; photometric check {verdict}: {figures}"
