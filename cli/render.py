"""``weathergen render``: turn a dataset (by default the demo scene) into its weather twin."""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import click
import torch
from rich.console import Console
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TaskProgressColumn,
                           TextColumn, TimeElapsedColumn)
from rich.text import Text
from rich.table import Table

from weathergen.datasets import in_research_frame
from weathergen.engine import parse_set_options, resolve_device
from weathergen.execution import RunClock, check_executor
from weathergen.outputs import FORMATS, folder_size
from weathergen.render import RenderJob, parse_shard, run_render
from weathergen.render.plan import default_batch_size, default_out, default_pass_name, resolve_preset
from weathergen.words import counted

from .options import (ARGV_KEY, RunOptions, dataset_options, device_option, executor_options,
                      gathered, job_exit_codes, out_option, overwrite_option, quiet_option,
                      render_compat_option, resume_option, seed_option)
from .stopping import exit_interrupted, terminate_as_interrupt

class _RateColumn(ProgressColumn):
    """Pairs per second (or seconds per pair when slower than one a second), of the pairs computed
    (the run's :class:`RunClock`; skipped and failed pairs are not its pace)."""

    def render(self, task):
        return Text(task.fields.get("rate", ""))


def _human_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"


def _parse_workers(ctx, param, value):
    if value is None or str(value).lower() == "auto":
        return 0
    try:
        n = int(value)
    except ValueError:
        raise click.BadParameter(f"{value!r}: a number of worker processes, or auto") from None
    if n < 1:
        raise click.BadParameter(f"{n}: at least 1 (or auto)")
    return n


@dataclass(frozen=True)
class OutputOptions:
    """What a render writes besides the weather frames (``--pass-name``, ``--format``,
    ``--geometry``, ``--sequence``, ``--stereo``, ``--particle-truth``), named as
    :class:`RenderJob`'s fields."""

    pass_name: Optional[str] = None
    fmt: str = "png"
    geometry: bool = True
    sequence: bool = False
    stereo: bool = False
    truth: bool = False


@click.command(epilog=job_exit_codes())
@dataset_options
@click.option("--preset", default=None,
              help="Weather preset by name (see `weathergen presets`); presets joined by + "
                   "render together in one pass, e.g. rain-heavy+fog-light. Default: snow; with "
                   "--particles of the paper's published weather, the preset its folder's name "
                   "says (particles_3000_npz: particles-3000).")
@click.option("--preset-file", type=click.Path(dir_okay=False, path_type=str), default=None,
              help="Your own preset file (TOML); replaces --preset. Default: none.")
@click.option("--set", "set_items", multiple=True, metavar="KEY=VALUE",
              help="Override one preset key (repeatable), e.g. --set count=500. Default: none.")
@out_option("out/<preset>")
@seed_option("Run seed; each pair's seed derives from it and the pair's identity.")
@click.option("--particles", "particles_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None, help="Re-render the particles of an earlier render output instead of sampling, "
                                  "or the paper's published weather (a set of the research "
                                  "code's SCENE/frame_NNNN.npz files; see docs/render.md). "
                                  "Default: sample new particles.")
@render_compat_option
@click.option("--pass-name", default=None,
              help="Name of the output pass folder. Default: <preset>_<input pass>.")
@device_option
@click.option("--workers", default="auto", show_default=True, callback=_parse_workers, metavar="N|auto",
              help="Worker processes rendering pairs side by side (CPU). Each pair renders on one "
                   "thread, so that the bytes do not depend on the machine; workers are what uses "
                   "more cores. They help on long runs with idle cores: each costs about 300 MB "
                   "and seconds to start. auto: one per core, at most one per 8 pairs to render, "
                   "1 on CUDA (so 1 for the demo scene).")
@click.option("--batch-size", type=click.IntRange(min=1), default=None,
              help="Pairs of the same size rendered together. Default: 8 on CUDA, 1 on CPU. "
                   "Does not change the output bytes.")
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="png",
              show_default=True, help="8-bit PNG frames, float OpenEXR frames with an opacity channel, or both.")
@click.option("--geometry/--no-geometry", default=True, show_default=True,
              help="Also write depth, cameras and flow per pair, so the output reads as a Sintel tree.")
@click.option("--sequence", is_flag=True,
              help="Render whole scenes with one weather field (field presets, or combinations "
                   "of them such as snow-light+fog-light): each frame once, "
                   "written into its scene as in the input, so consecutive frames make pairs. "
                   "Default: each pair its own two-frame scene.")
@click.option("--stereo", is_flag=True,
              help="Also render the same particles into the dataset's second camera (KITTI image_3, "
                   "Spring's right view), written to <pass>_right. Default: off.")
@click.option("--particle-truth", "truth", is_flag=True,
              help="Also write the particle layer's flow and opacity and the seen flow per pair "
                   "(see docs/render.md). Default: off.")
@click.option("--shard", default="1/1", show_default=True, metavar="I/N",
              help="Render only shard I of N (for job arrays); parts merge into one manifest.")
@executor_options
@resume_option("Finish an interrupted run (same options): skip the pairs that are complete.")
@overwrite_option("Redo every pair, even in a folder that holds a render, and write into a non-empty "
                  "folder that render did not create.")
@quiet_option
@gathered("outputs", OutputOptions)
@gathered("run", RunOptions)
def render(dataset, preset, preset_file, set_items, out, seed, particles_dir, compat, workers,
           shard, quiet, run: RunOptions, outputs: OutputOptions):
    """Render weather into every selected frame pair and write frames plus particle metadata.

    With no option it renders the snow preset onto the bundled demo scene into out/snow.
    """
    check_executor(run.executor)
    if compat == "reference":
        dataset = in_research_frame(dataset)
    # A Ray driver need not have the workers' devices.
    dev = (resolve_device(run.device) if run.executor == "local"
           else torch.device("cuda" if run.device.startswith("cuda") else "cpu"))
    run = dataclasses.replace(run, batch_size=run.batch_size or default_batch_size(dev))
    preset_obj, name, appearance = resolve_preset(preset, preset_file, parse_set_options(set_items),
                                                  particles_dir)
    outputs = dataclasses.replace(outputs, pass_name=outputs.pass_name or
                                  default_pass_name(name, dataset.selection.pass_))
    job = RenderJob(
        dataset=dataset, out=out or default_out(name), preset=preset_obj, preset_name=name,
        seed=seed, particles_from=particles_dir, appearance=appearance, shard=parse_shard(shard),
        workers=workers, compat=compat or "paper", **dataclasses.asdict(run),
        **dataclasses.asdict(outputs),
        command=click.get_current_context().meta.get(ARGV_KEY, ["weathergen", *sys.argv[1:]]),
    )
    report = _Report(Console(stderr=False), quiet)
    t0 = time.perf_counter()
    report.run(job)
    _summary(job, report.results, time.perf_counter() - t0, report.console, quiet)


class _Report:
    """What a render says while it runs: a progress bar on a terminal, else a line per pair;
    failed pairs and warnings one line each, on stderr; the pairs' results kept in order."""

    def __init__(self, console: Console, quiet: bool):
        self.console, self.quiet = console, quiet
        self.results: list = []
        self.clock: Optional[RunClock] = None
        self.progress = None
        self.task = None
        if console.is_terminal and not quiet:
            self.progress = Progress(
                TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                TaskProgressColumn(), _RateColumn(), TimeElapsedColumn(),
                TextColumn("{task.fields[left]}"), TextColumn("{task.fields[pair]}"),
                console=console)

    def run(self, job: RenderJob) -> None:
        """Run the render job, reporting; a stop (Ctrl-C, SIGTERM) says how far it got."""
        stopped_by = None
        try:
            with terminate_as_interrupt() as stopped_by:
                with self.progress if self.progress is not None else contextlib.nullcontext():
                    run_render(job, self.on_result, self.on_start, self.on_note)
        except KeyboardInterrupt:
            exit_interrupted(sum(r.status == "written" for r in self.results), stopped_by)

    def on_start(self, n: int) -> None:
        self.clock = RunClock(n)
        if self.progress is not None:
            self.task = self.progress.add_task("render", total=n, pair="", rate="", left="")

    @staticmethod
    def on_note(text: str) -> None:
        click.echo(f"Note: {text}", err=True)

    def on_result(self, r) -> None:
        self.results.append(r)
        self.clock.add(computed=r.status == "written")
        if r.status == "failed":   # one unwrapped line, so paths stay whole
            self._line("red", "failed", f"{r.pair}: {r.message}")
        for text in r.warnings:    # written, but the input looks wrong
            self._line("yellow", "warning", f"{r.pair}: {text}")
        if self.progress is not None:
            self.progress.update(self.task, advance=1, pair=r.pair, rate=self.clock.pace(),
                                 left=self.clock.time_left())
        elif not self.quiet:
            self.console.print(f"[{self.clock.describe()}] {r.pair} {r.status} ({r.seconds:.2f} s)",
                               highlight=False, soft_wrap=True)

    def _line(self, colour: str, word: str, text: str) -> None:
        """One line on stderr (above the progress bar where there is one)."""
        if self.progress is not None:
            self.progress.console.print(f"[{colour}]{word}[/{colour}] {text}", highlight=False,
                                        soft_wrap=True)
        else:
            click.echo(f"{word} {text}", err=True)


def _summary(job: RenderJob, results: list, elapsed: float, console: Console, quiet: bool) -> None:
    """The run's table and where its output is; exit 1 when a pair failed."""
    written = [r for r in results if r.status == "written"]
    failed = [r for r in results if r.status == "failed"]
    if not quiet:
        table = Table(title=f"weathergen render: {job.preset_name} -> {job.out}")
        for col in ("written", "skipped", "failed", "time per pair", "written size", "total time"):
            table.add_column(col, justify="right")
        per_pair = sum(r.seconds for r in written) / len(written) if written else 0.0
        table.add_row(str(len(written)), str(sum(r.status == "skipped" for r in results)),
                      str(len(failed)), f"{per_pair:.2f} s", _human_bytes(sum(r.bytes for r in written)),
                      f"{elapsed:.1f} s")
        console.print(table)
        console.print(f"Output: {job.out} (pass '{job.pass_name}', "
                      f"{_human_bytes(folder_size(job.out))} in all; manifest: "
                      f"{job.out / 'manifest.json'})", highlight=False, soft_wrap=True)
    if failed:
        Console(stderr=True).print(f"[red]{counted(len(failed), 'pair')} failed[/red]; see the "
                                   "messages above and the manifest.")
        sys.exit(1)
