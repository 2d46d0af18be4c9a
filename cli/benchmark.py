"""``weathergen benchmark``: the paper's tables in one command."""

from __future__ import annotations

import sys
from pathlib import Path

import click
from rich.console import Console

from weathergen.attack import EarlyStop, run_attack
from weathergen.benchmark import (DEFAULT_LP, DEFAULT_PRESETS, BenchmarkSpec, available_ladders, run_grid,
                                  tr115_default, write_tables)
from weathergen.datasets import in_research_frame
from weathergen.engine import parse_set_options, resolve_device
from weathergen.errors import ConfigError
from weathergen.render.shards import parse_shard

from .options import (BAD_INPUT, amp_option, attack_steps, compat_option, dataset_options, early_stop_option,
                      precision_option,
                      device_option, exit_codes, quiet_option, seed_option)
from .stopping import exit_interrupted, terminate_as_interrupt


def _names(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def _checkpoints(items) -> dict:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise ConfigError(f"${{checkpoint}} {item!r}: expected NETWORK=FILE_OR_NAME")
        out[name.strip()] = value.strip()
    return out


@click.command(epilog=exit_codes(
    ("0", "every cell of the grid run (pairs that failed are recorded in its cells' manifests) "
          "and the tables written"),
    BAD_INPUT,
    ("130, 143", "stopped by Ctrl-C / SIGTERM: the finished pairs are kept; the same command "
                 "finishes the grid")))
@dataset_options
@click.option("--networks", default="raft", show_default=True, metavar="A,B,...",
              help="Flow networks (comma-separated), one table column each: names as for "
                   "`attack --model`, networks of your own as FILE.py:NAME or "
                   "package.module:NAME too.")
@click.option("--checkpoint", "checkpoint_items", multiple=True, metavar="NETWORK=CKPT",
              help="Checkpoint file or name of one network (repeatable). Default: its own.")
@click.option("--presets", default=None, metavar="A,B,...",
              help="Weather presets (random and adversarial; combinations such as "
                   "snow-light+fog-light too) or attack configurations of the supplement "
                   "(grey-offset1 ... grey-all: the paper's Table 3); '' for none. Default: "
                   f"{','.join(DEFAULT_PRESETS)}, none with --ladder.")
@click.option("--lp", "lp_text", default=None, metavar="A,B,...",
              help=f"Lp attacks (pcfa, ifgsm); '' for none. Default: {','.join(DEFAULT_LP)}, "
                   "none with --ladder.")
@click.option("--ladder", "ladder_text", default=None, metavar="A,B,...",
              help=f"Severity ladders ({', '.join(available_ladders())}): each weather's -light, "
                   "-moderate and -heavy presets, random and adversarial, one curve per network "
                   "(ladders.csv, ladder.png) and its robustness score (robustness.csv).")
@click.option("--steps", type=int, default=None, callback=attack_steps,
              help="Weather attack steps per pair (at least 1). Default: the attack's (750).")
@click.option("--lp-steps", type=int, default=None, callback=attack_steps,
              help="Lp attack steps per pair (at least 1). Default: each method's (pcfa 20, ifgsm 25).")
@click.option("--iters", type=click.IntRange(min=1), default=None,
              help="Refinement iterations of recurrent networks. Default: each network's.")
@click.option("--set", "set_items", multiple=True, metavar="KEY=VALUE",
              help="Override one preset key in every weather run (repeatable).")
@click.option("--shard", "shard_text", default=None, metavar="I/N",
              help="Run only every N-th run of the grid, starting at the I-th (job arrays); the "
                   "tables cover whatever is finished.")
@click.option("--download", is_flag=True,
              help="Fetch named checkpoints that are missing from the cache (needs a network).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path),
              default=Path("out/benchmark"), show_default=True, help="Benchmark folder.")
@compat_option
@early_stop_option
@seed_option("Run seed of every run (weather as `weathergen render --seed`).")
@device_option
@amp_option
@precision_option
@quiet_option
def benchmark(dataset, networks, checkpoint_items, presets, lp_text, ladder_text, steps, lp_steps, iters,
              set_items, shard_text, download, out, compat, early_stop, seed, device, amp, precision,
              quiet):
    """Run networks x {random weather, adversarial weather, Lp attacks} x presets and write
    the paper's tables (CSV, JSON, Markdown, LaTeX; one file per table in OUT/tables) and a plot
    of AEE per network and preset (OUT/aee.png) into OUT; with --ladder also each network's
    curve over the severities and its robustness score.

    Without --frames-per-scene at most 5 pairs per scene are used (the
    paper's Sintel-tr115 on Sintel training). Every run is an `attack` output under OUT/runs;
    running the command again resumes where it stopped.
    """
    resolve_device(device)
    if compat == "reference":           # the research code's frame and scaling too
        dataset = in_research_frame(dataset)
    ladders = _names(ladder_text or "")
    if ladder_text is not None and not ladders:
        raise ConfigError(f"${{ladder}} {ladder_text!r} names no ladder: expected "
                          f"{', '.join(available_ladders())}")
    spec = BenchmarkSpec(
        dataset=tr115_default(dataset), out=out, networks=_names(networks),
        presets=_names(presets) if presets is not None else [] if ladders else list(DEFAULT_PRESETS),
        lp_methods=_names(lp_text) if lp_text is not None else [] if ladders else list(DEFAULT_LP),
        ladders=ladders,
        checkpoints=_checkpoints(checkpoint_items), steps=steps, lp_steps=lp_steps, iters=iters,
        overrides=parse_set_options(set_items), seed=seed, device=device, download=download,
        amp=amp, precision=precision, command=["weathergen", *sys.argv[1:]], compat=compat or "paper",
        early_stop=None if early_stop is None else EarlyStop.parse(early_stop))
    for network in spec.resolved.values():
        if network.note():
            click.echo(f"Note: {network.note()}", err=True)
    shard = parse_shard(shard_text) if shard_text else None
    console = Console()

    written = []

    def on_cell(i, n, cell):
        if not quiet:
            console.print(f"[{i + 1}/{n}] {cell.network} {cell.label}", highlight=False)

    def on_pair_done(report):
        if report.status == "written":
            written.append(report.pair)

    on_note = _note_once()

    def execute(job):
        return run_attack(job, on_pair_done=on_pair_done, on_note=on_note)

    stopped_by = None
    try:
        with terminate_as_interrupt() as stopped_by:
            run_grid(spec, shard, execute=execute, on_cell=on_cell)
            paths = write_tables(spec)      # atomic files: a stop leaves the earlier ones
    except KeyboardInterrupt:
        # every run of the grid resumes by itself: the same command finishes it
        exit_interrupted(len(written), stopped_by, again="rerun the same command")
    if not quiet:
        _print_tables(console, paths, out)


def _note_once():
    """A note printer that says each note once (each cell's run lists the same dataset)."""
    noted: set = set()

    def on_note(text):
        if text not in noted:
            noted.add(text)
            click.echo(f"Note: {text}", err=True)

    return on_note


def _print_tables(console, paths: dict, out) -> None:
    """The Markdown tables, then where every file of the benchmark is."""
    console.print(paths["markdown"].read_text(), highlight=False, markup=False)
    console.print(f"Tables: {paths['markdown']}, {paths['latex']} (one file per table in "
                  f"{Path(out) / 'tables'}); plot: {paths['plot']}; results: {paths['csv']}, "
                  f"{paths['json']}", highlight=False, soft_wrap=True)
    if "curves" in paths:
        console.print(f"Severity ladders: curves {paths['curves']}, scores {paths['scores']}, "
                      f"plot {paths['ladder_plot']}", highlight=False, soft_wrap=True)
