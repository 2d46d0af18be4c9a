"""``weathergen render``: turn a dataset (by default the demo scene) into its weather twin."""

from __future__ import annotations

import sys
import time
from pathlib import Path

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

from .options import (ARGV_KEY, dataset_options, device_option, executor_options, job_exit_codes,
                      out_option, overwrite_option, quiet_option, render_compat_option,
                      resume_option, seed_option)
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
def render(dataset, preset, preset_file, set_items, out, seed, particles_dir, compat, pass_name, device,
           workers, batch_size, fmt, geometry, sequence, stereo, truth, shard, executor, ray_address,
           resume, overwrite,
           quiet):
    """Render weather into every selected frame pair and write frames plus particle metadata.

    With no option it renders the snow preset onto the bundled demo scene into out/snow.
    """
    check_executor(executor)
    if compat == "reference":
        dataset = in_research_frame(dataset)
    # A Ray driver need not have the workers' devices.
    dev = (resolve_device(device) if executor == "local"
           else torch.device("cuda" if device.startswith("cuda") else "cpu"))
    batch_size = batch_size or default_batch_size(dev)
    preset_obj, name, appearance = resolve_preset(preset, preset_file, parse_set_options(set_items),
                                                  particles_dir)
    out = out or default_out(name)
    job = RenderJob(
        dataset=dataset, out=out, preset=preset_obj, preset_name=name, seed=seed,
        pass_name=pass_name or default_pass_name(name, dataset.selection.pass_), fmt=fmt,
        geometry=geometry, truth=truth, sequence=sequence, stereo=stereo,
        device=device, particles_from=particles_dir, appearance=appearance,
        shard=parse_shard(shard), workers=workers, batch_size=batch_size, resume=resume, overwrite=overwrite,
        executor=executor, ray_address=ray_address, compat=compat or "paper",
        command=click.get_current_context().meta.get(ARGV_KEY, ["weathergen", *sys.argv[1:]]),
    )
    console = Console(stderr=False)
    err = Console(stderr=True)
    results = []
    t0 = time.perf_counter()
    interactive = console.is_terminal and not quiet
    progress = None
    task = None

    clock = None

    def on_start(n):
        nonlocal task, clock
        clock = RunClock(n)
        if progress is not None:
            task = progress.add_task("render", total=n, pair="", rate="", left="")

    def on_note(text):
        click.echo(f"Note: {text}", err=True)

    def on_result(r):
        results.append(r)
        clock.add(computed=r.status == "written")
        if r.status == "failed":   # one unwrapped line, so paths stay whole
            if progress is not None:
                progress.console.print(f"[red]failed[/red] {r.pair}: {r.message}", highlight=False,
                                       soft_wrap=True)
            else:
                click.echo(f"failed {r.pair}: {r.message}", err=True)
        for text in r.warnings:    # written, but the input looks wrong
            if progress is not None:
                progress.console.print(f"[yellow]warning[/yellow] {r.pair}: {text}", highlight=False,
                                       soft_wrap=True)
            else:
                click.echo(f"warning {r.pair}: {text}", err=True)
        if progress is not None:
            progress.update(task, advance=1, pair=r.pair, rate=clock.pace(), left=clock.time_left())
        elif not quiet:
            console.print(f"[{clock.describe()}] {r.pair} {r.status} ({r.seconds:.2f} s)",
                          highlight=False, soft_wrap=True)

    if interactive:
        progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TaskProgressColumn(), _RateColumn(), TimeElapsedColumn(),
                            TextColumn("{task.fields[left]}"), TextColumn("{task.fields[pair]}"),
                            console=console)
    stopped_by = None
    try:
        with terminate_as_interrupt() as stopped_by:
            if progress is not None:
                with progress:
                    run_render(job, on_result, on_start, on_note)
            else:
                run_render(job, on_result, on_start, on_note)
    except KeyboardInterrupt:
        exit_interrupted(sum(r.status == "written" for r in results), stopped_by)
    elapsed = time.perf_counter() - t0
    written = [r for r in results if r.status == "written"]
    failed = [r for r in results if r.status == "failed"]
    if not quiet:
        table = Table(title=f"weathergen render: {name} -> {out}")
        for col in ("written", "skipped", "failed", "time per pair", "written size", "total time"):
            table.add_column(col, justify="right")
        per_pair = sum(r.seconds for r in written) / len(written) if written else 0.0
        table.add_row(str(len(written)), str(sum(r.status == "skipped" for r in results)),
                      str(len(failed)), f"{per_pair:.2f} s", _human_bytes(sum(r.bytes for r in written)),
                      f"{elapsed:.1f} s")
        console.print(table)
        console.print(f"Output: {out} (pass '{job.pass_name}', {_human_bytes(folder_size(out))} in all; "
                      f"manifest: {out / 'manifest.json'})", highlight=False, soft_wrap=True)
    if failed:
        err.print(f"[red]{counted(len(failed), 'pair')} failed[/red]; see the messages above and the manifest.")
        sys.exit(1)
