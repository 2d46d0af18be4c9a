"""``weathergen evaluate``: how much rendered weather changes a flow network's output."""

from __future__ import annotations

from pathlib import Path

import click
from rich.console import Console
from rich.table import Table

from weathergen.attack import default_evaluation_path, run_evaluation, write_evaluation
from weathergen.attack.record import run_settings, settings_text
from weathergen.engine import resolve_device
from weathergen.models import AUTOCAST, get_model, resolve_precision
from weathergen.datasets import load_scene_scales, open_dataset
from weathergen.errors import ConfigError
from weathergen.io.published_weather import is_published_set
from weathergen.outputs import PublishedWeatherSet, WeatherFolder, read_manifest
from weathergen.render import published_preset, resolve_preset

from .attack import region_rows
from .options import (BAD_INPUT, STOPPED, ModelOptions, device_option, exit_codes, gathered,
                      model_options, quiet_option, resolve_model)


def _fmt(value) -> str:
    return "–" if value is None else f"{value:.3f}"


@click.command(epilog=exit_codes(("0", "every complete pair evaluated, the figures written"),
                                  BAD_INPUT, STOPPED))
@click.option("--weather", "weather_dir", required=True,
              type=click.Path(file_okay=False, path_type=Path),
              help="Folder written by `weathergen render` (or `weathergen attack`).")
@model_options
@click.option("--dataset", "dataset_name", default=None,
              help="Dataset of the clean frames. Default: as recorded in the weather folder.")
@click.option("--root", default=None, type=click.Path(path_type=str),
              help="Where the clean dataset is stored. Default: as recorded.")
@click.option("--pass", "pass_", default=None,
              help="Clean pass (Sintel: clean or final). Default: as recorded.")
@click.option("--preset", default=None,
              help="The paper's published weather (--weather a set of the research code's "
                   "particle files): the preset it is drawn with. Default: the one the set's "
                   "folder name says (particles_3000_npz: particles-3000).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="Write the figures here. Default: WEATHER/evaluate-<model>.json (a network of "
                   "your own: evaluate-<file stem>.<NAME>.json); for a published set, which is "
                   "left as it is, evaluate-<set>-<model>.json in the working folder.")
@device_option
@quiet_option
@gathered("net", ModelOptions)
def evaluate(weather_dir, dataset_name, root, pass_, preset, json_path, device, quiet,
             net: ModelOptions):
    """Robustness to weather: AEE(f, f̌) between the flow on clean and on weather frames.

    Also reports the end-point error against ground truth, for the clean and the weather frames,
    where the dataset has it, both figures on the pixels the weather covers (its opacity above
    1/255 in either frame) and on the rest, and KITTI's Fl-all and 1/3/5 px outlier rates of the
    weather flow. All figures are in pixels, rates in percent.
    """
    resolve_device(device)
    model = resolve_model(net.model, net.model_input)
    precision = resolve_precision(model, net.precision, net.amp, device)
    if is_published_set(weather_dir):
        folder = open_published(weather_dir, preset, dataset_name, root, pass_)
    else:
        if preset is not None:
            raise click.UsageError("--preset applies to the paper's published weather only; a "
                                   "weathergen folder records its preset")
        folder = WeatherFolder.open(weather_dir)
    dataset = folder.clean_dataset(dataset_name, root, pass_)
    network = get_model(model, net.checkpoint, device=device, iters=net.iters,
                        download=net.download, precision=precision)
    console = Console()

    def on_pair(row):
        if not quiet:
            console.print(f"{row.pair}: AEE(f, f̌) {row.aee_weather:.3f}", highlight=False,
                          soft_wrap=True)

    rows, summary = run_evaluation(network, folder, dataset, device, on_pair)
    info = {"model": model.name, "checkpoint": net.checkpoint, "iters": net.iters,
            "amp": precision in AUTOCAST, "precision": precision,
            "weather": str(weather_dir), "pass": folder.pass_name, "clean": dataset.describe()}
    source = model.source()
    if source is not None:
        info["source"] = source
    published = isinstance(folder, PublishedWeatherSet)
    if published:
        info["published"] = {"preset": folder.preset_name}
    info["settings"] = run_settings(
        model, net.checkpoint, iters=getattr(network, "iters", net.iters), precision=precision,
        padding=network.padding,
        seed=None if published else read_manifest(weather_dir, "weather").data.get("seed"))
    json_path = json_path or default_evaluation_path(weather_dir, model.label, published)
    write_evaluation(json_path, info, rows, summary)
    if quiet:
        return
    console.print(_table(f"weathergen evaluate: {model.label} on {weather_dir} (pixels)", rows,
                         summary))
    for label, value in region_rows(summary):
        console.print(f"{label}: {value}", highlight=False, soft_wrap=True)
    console.print(f"Settings: {settings_text(info['settings'])}", highlight=False, soft_wrap=True)
    console.print(f"Figures: {json_path}", highlight=False, soft_wrap=True)


def _table(title: str, rows, summary: dict) -> Table:
    """One row per pair, then their means."""
    table = Table(title=title)
    for i, col in enumerate(("pair", "AEE(f, f̌)", "EPE clean", "EPE weather")):
        table.add_column(col, justify="left" if i == 0 else "right")
    for r in rows:
        table.add_row(r.pair, _fmt(r.aee_weather), _fmt(r.epe_clean), _fmt(r.epe_weather))
    table.add_section()
    table.add_row(f"mean of {summary['pairs']}", _fmt(summary["aee_weather"]),
                  _fmt(summary["epe_clean"]), _fmt(summary["epe_weather"]))
    return table

def open_published(folder, preset, dataset_name, root, pass_) -> PublishedWeatherSet:
    """A published set against the clean dataset at ``root`` (Sintel unless named), opened in
    the research code's frame and scaling, where its particles were placed."""
    if root is None:
        raise ConfigError(f"{folder} holds the paper's published weather (particles, no record of "
                          f"the dataset): give the clean dataset with ${{root}}")
    if preset is None and published_preset(folder) is None:
        raise ConfigError(f"${{weather}} {folder}: published weather does not record the preset "
                          f"it was generated with, and the folder's name does not say: name it "
                          f"with ${{preset}} (e.g. particles-3000)")
    resolved = resolve_preset(preset, None, None, folder)
    dataset = open_dataset(dataset_name or "sintel", root, pass_=pass_ or "clean",
                           scene_scales=load_scene_scales("research"), camera_translation="unscaled")
    return PublishedWeatherSet.open(folder, dataset, resolved.preset, resolved.name)
