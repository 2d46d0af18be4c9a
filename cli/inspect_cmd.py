"""``weathergen inspect FILE`` and ``weathergen preview DIR`` (a contact sheet, or ``--video``):
look at what a render wrote."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import click
import numpy as np
from rich.console import Console
from rich.table import Table

from weathergen.datasets import frame_rates_text
from weathergen.engine import FrameScaling
from weathergen.engine.records.layered import layer_arrays
from weathergen.engine.records.particles import LAYERED_FORMAT_VERSION, TENSOR_FIELDS, Particles, stored_as
from weathergen.errors import ConfigError
from weathergen.io.atomic import remove_temporaries, write_error
from weathergen.io.published_weather import is_published_file, read_published_weather
from weathergen.io.images import write_png
from weathergen.io.video import check_video_path, write_video
from weathergen.outputs import read_metadata, stored_frame_scaling
from weathergen.render import contact_sheet, video_preview
from weathergen.render.preview import MAX_TILE_WIDTH
from weathergen.render.video import MAX_CYCLES, MAX_FPS, MIN_FPS, MIN_SECONDS, PAIR_FPS, PAIR_SECONDS
from weathergen.words import counted

from .options import BAD_INPUT, STOPPED, exit_codes


@click.command(epilog=exit_codes(("0", "shown"), ("2", "the file cannot be read (one line)"),
                                 STOPPED))
@click.argument("file", type=click.Path(dir_okay=False, path_type=Path))
def inspect(file: Path):
    """Show what a particle-metadata file holds: pair, seed, preset, counts and value ranges
    (per layer for a combined preset); or a particle file of the paper's published weather (the
    research code's format)."""
    console = Console()
    if is_published_file(file):
        _published(console, file)
        return
    arrays = read_metadata(file)
    if "format_version" not in arrays and "lp_attack" in arrays:
        console.print(_lp_head(arrays, file))     # an Lp attack perturbs the frames: no particles
        return
    source = (json.loads(str(arrays["preset"])) if "preset" in arrays else {}).get("source", "")
    layered = int(arrays.get("format_version", 0)) == LAYERED_FORMAT_VERSION
    if layered:
        names = [str(n) for n in np.atleast_1d(arrays["layer_names"])]
        layers = [layer_arrays(arrays, k) for k in range(len(names))]
    else:
        names, layers = [""], [arrays]
    counts = [int(a["position"].shape[0]) if "position" in a else 0 for a in layers]
    scaling = stored_frame_scaling(arrays, file)
    scalings = (scaling or {}).get("layers", [None] * len(layers)) if layered else [scaling]
    head = Table(title=str(file), show_header=False)
    head.add_column("key")
    head.add_column("value")
    rows = [
        ("pair", f"{arrays['pair_dataset']}/{arrays['pair_split']}/{arrays['pair_scene']} "
                 f"frame {int(arrays['pair_frame'])}"),
        ("seed", str(int(arrays["seed"]))),
        ("preset", str(arrays["preset_name"]) + ("" if not source or source.startswith("preset ")
                                                  else f" (from {source})")),   # a user's file
        ("particles", str(sum(counts))),
        ("for the frame", _scaling_text(scalings[0]) if not layered else "per layer, below"),
        ("visible in frame 1 / 2", f"{int(arrays['visible1'])} / {int(arrays['visible2'])}"
                                   if "visible1" in arrays else "not recorded"),
    ]
    rows += (_layer_rows(arrays, names, layers, counts, scalings) if layered
             else _record_rows(arrays))
    version = int(layers[0].get("format_version", 0))
    rows += [
        ("format", f"metadata v{int(arrays['metadata_version'])}, particles v{version}"
                   f"{f' in layers (v{LAYERED_FORMAT_VERSION})' if layered else ''}, "
                   f"written by weathergen {arrays.get('weathergen_version', '?')}"),
        ("file size", f"{file.stat().st_size:,} bytes"),
    ]
    for k, v in rows:
        head.add_row(k, v)
    console.print(head)
    for name, a in zip(names, layers):
        title = f"per-particle values{f' of layer {name}' if name else ''} (as Particles.load reads them)"
        console.print(_ranges(a, title, file))


def _layer_rows(arrays: dict, names: list, layers: list, counts: list, scalings: list) -> list:
    """The rows of a combined preset's layers: each layer's look, seed and frame scaling."""
    rows = []
    seeds = np.atleast_1d(arrays.get("layer_seeds", np.zeros(0, np.uint64)))
    for k, (name, a, n) in enumerate(zip(names, layers, counts)):
        seed = f", seed {int(seeds[k])}" if k < len(seeds) else ""
        rows.append((f"layer {k}", f"{name}: {counted(n, 'particle')}, {_looks(a)}{seed}"))
        rows.append((f"layer {k} for the frame", _scaling_text(scalings[k])))
    rows.append(("reference frame", str(layers[0].get("frame", "?"))))
    return rows


def _record_rows(arrays: dict) -> list:
    """The rows of one record's look: reference frame, blend, motion blur and templates."""
    return [
        ("reference frame", str(arrays.get("frame", "?"))),
        ("blend", str(arrays.get("blend", "?"))),
        ("motion blur", f"length {float(arrays.get('blur_length', 0)):g}, "
                        f"{int(arrays.get('blur_samples', 1))} samples"),
        ("templates", str(arrays.get("templates", "?")) if "stamp_boxes" not in arrays else
         f"none: each particle's own stored stamp ({int(arrays['stamp_side'])} px square, "
         f"from the paper's published weather)"),
    ]


def _published(console: Console, file: Path) -> None:
    """A particle file of the paper's published weather: the pair it names, its particles' values
    in the research code's terms, and how weathergen draws it."""
    w = read_published_weather(file)
    head = Table(title=str(file), show_header=False)
    head.add_column("key")
    head.add_column("value")
    extent = [int(np.count_nonzero((a > 0).any(0))) for a in w.alpha]
    for key, value in (
            ("format", "the paper's research code (save_weatherfile): points3D, motion3D, flakes, "
                       "flakescol, flakestrans; weathergen reads it as published weather"),
            ("pair", f"scene {file.parent.name}, frame {file.stem.removeprefix('frame_')} "
                     f"(and the next)"),
            ("particles", str(w.count)),
            ("flakes", f"{w.side} px square each, alpha drawn {min(extent, default=0)} to "
                       f"{max(extent, default=0)} px wide; no colour offsets"),
            ("drawn by weathergen", "render --particles SET (its folder), with the preset it was "
                                    "generated with; docs/render.md"),
            ("file size", f"{file.stat().st_size:,} bytes")):
        head.add_row(key, value)
    console.print(head)
    ranges = Table(title="per-particle values (as the file holds them)")
    for col in ("value", "shape", "min", "max", "mean"):
        ranges.add_column(col, justify="left" if col in ("value", "shape") else "right", no_wrap=True)
    theta = (np.tanh(w.transparency.astype(np.float64)) + 1) / 2
    for label, values in (("position x, y, z (camera 1)", w.points), ("depth z (camera 1)", w.points[:, 2]),
                          ("motion x, y, z (camera 2 axes)", w.motion), ("colour r, g, b", w.color),
                          ("transparency (before tanh)", w.transparency),
                          ("θ / s = (tanh + 1) / 2", theta), ("flake alpha", w.alpha)):
        v = np.asarray(values, np.float64)
        ranges.add_row(label, str(tuple(v.shape)), *(f"{f(v):.4g}" if v.size else "–"
                                                     for f in (np.min, np.max, np.mean)))
    console.print(ranges)


def _lp_head(arrays: dict, file: Path) -> Table:
    """The table of an Lp attack's metadata file: the pair, the seed, the attack's settings."""
    head = Table(title=str(file), show_header=False)
    head.add_column("key")
    head.add_column("value")
    settings = json.loads(str(arrays["lp_attack"]))
    rows = [
        ("pair", f"{arrays['pair_dataset']}/{arrays['pair_split']}/{arrays['pair_scene']} "
                 f"frame {int(arrays['pair_frame'])}"),
        ("seed", str(int(arrays["seed"]))),
        ("Lp attack", ", ".join(f"{k} {v}" for k, v in settings.items())),
        ("particles", "none (the attack perturbs the frames themselves)"),
        ("format", f"metadata v{int(arrays['metadata_version'])}, written by weathergen "
                   f"{arrays.get('weathergen_version', '?')}"),
        ("file size", f"{file.stat().st_size:,} bytes"),
    ]
    for k, v in rows:
        head.add_row(k, v)
    return head


def _scaling_text(scaling) -> str:
    """How a paper preset's count and size were set for the pair's frame (the metadata's
    ``frame_scaling`` entry), in one line."""
    if not scaling:
        return "not recorded (a weather field, or written before frame scaling: the preset's count)"
    return FrameScaling.from_dict(scaling).describe()


def _looks(arrays: dict) -> str:
    """Blend, motion blur and templates of a record's file entries, in one line."""
    return (f"{arrays.get('blend', '?')} blend, motion blur length "
            f"{float(arrays.get('blur_length', 0)):g} in {int(arrays.get('blur_samples', 1))} "
            f"samples, templates {arrays.get('templates', '?')}")


def _ranges(arrays: dict, title: str, path: Path) -> Table:
    """Every per-particle field of one record's file entries as a user reads it (the dtype, shape
    and values :meth:`Particles.from_arrays` gives, codes decoded), and how the file stores it."""
    record = Particles.from_arrays(arrays, path)
    ranges = Table(title=title)
    for col in ("field", "dtype", "shape", "min", "max", "mean", "stored as"):
        ranges.add_column(col, justify="right" if col in ("min", "max", "mean") else "left",
                          no_wrap=True)
    for name in TENSOR_FIELDS:
        t = getattr(record, name)
        if t.numel():
            f = t.double()
            stats = (f"{f.min().item():.4g}", f"{f.max().item():.4g}", f"{f.mean().item():.4g}")
        else:
            stats = ("-", "-", "-")
        ranges.add_row(name, str(t.dtype).removeprefix("torch."), "×".join(map(str, t.shape)),
                       *stats, stored_as(arrays, name))
    return ranges


@click.command(epilog=exit_codes(
    ("0", "written"),
    ("1", "written, but some pairs were left out: their particle files cannot be read (each "
          "named)"),
    BAD_INPUT, STOPPED))
@click.argument("render_dir", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Contact sheet (PNG) to write. Default: RENDER_DIR/preview.png.")
@click.option("--video", type=click.Path(dir_okay=False, path_type=Path), default=None,
              metavar="FILE.mp4|FILE.gif",
              help="Write a video instead of the contact sheet: a --sequence output's frames in "
                   "order at the dataset's frame rate, an output of pairs as frame 1 / frame 2 "
                   f"alternating at {PAIR_FPS:g} frames per second. A video shorter than "
                   f"{MIN_SECONDS:g} s plays again until it lasts that long.")
@click.option("--pairs", type=click.IntRange(min=1), default=None,
              help="Pairs to show (the first ones). Default: 4 on the contact sheet (it says when "
                   "there are more), all in a video.")
@click.option("--width", type=click.IntRange(64, MAX_TILE_WIDTH), default=None,
              help="Width of each tile. Default: 480 on the contact sheet, the frames' own in a "
                   "video.")
@click.option("--with-input", is_flag=True,
              help="--video: show the clean input frame left of the weather frame.")
@click.option("--with-opacity", is_flag=True,
              help="--video: show the particles' opacity right of the weather frame.")
@click.option("--fps", type=click.FloatRange(MIN_FPS, MAX_FPS), default=None,
              help=f"--video: frames per second. Default: for a --sequence output the dataset's "
                   f"({frame_rates_text()}) or a field preset's frame_rate; for pairs {PAIR_FPS:g}.")
@click.option("--cycles", type=click.IntRange(1, MAX_CYCLES), default=None,
              help="--video of pairs: how often each pair shows frame 1 and frame 2. "
                   f"Default: for {PAIR_SECONDS:g} s.")
@click.option("--captions/--no-captions", default=True, show_default=True,
              help="--video: scene, frame and preset written on the tiles.")
def preview(render_dir: Path, out, video, pairs, width, with_input, with_opacity, fps, cycles,
            captions):
    """Write a contact sheet of a render output (original, weather frame and particle opacity),
    or with --video a video of it (MP4 or GIF)."""
    if video is not None:
        _preview_video(render_dir, out, video, pairs, width, with_input, with_opacity, fps, cycles,
                       captions)
        return
    for flag, given in (("with_input", with_input), ("with_opacity", with_opacity),
                        ("fps", fps is not None), ("cycles", cycles is not None),
                        ("captions", not captions)):
        if given:
            raise ConfigError(f"${{{flag}}} applies to ${{video}} only (the contact sheet always "
                              "shows the input, the weather and the opacity)")
    sheet = contact_sheet(render_dir, pairs=pairs or 4, width=width or 480)
    out = out or render_dir / "preview.png"
    remove_temporaries(out)         # those of an earlier preview that was killed
    try:
        write_png(out, sheet.image)
    except OSError as exc:
        raise write_error(exc, out, "pass --out PATH.png to write it elsewhere") from None
    if sheet.partial:
        click.echo(f"Preview of {sheet.shown} of {counted(sheet.total, 'pair')} written to {out} "
                   f"(--pairs {sheet.total} shows all)")
    else:
        click.echo(f"Preview of {counted(sheet.total, 'pair')} written to {out}")
    _left_out(sheet.unreadable)


def _left_out(unreadable: list[str]) -> None:
    """One warning line per pair a preview left out (its particle file cannot be read); exit 1
    when there is any."""
    for line in unreadable:
        click.echo(f"warning: {line}", err=True)
    if unreadable:
        sys.exit(1)


def _preview_video(render_dir: Path, out, video: Path, pairs, width, with_input, with_opacity,
                   fps, cycles, captions):
    if out is not None:
        raise ConfigError("${out} names the contact sheet; with ${video} give only the video file")
    check_video_path(video)          # before any work
    plan = video_preview(render_dir, pairs=pairs, cycles=cycles, fps=fps, with_input=with_input,
                         with_opacity=with_opacity, width=width, captions=captions)
    try:
        count = write_video(video, plan.frames(progress=ProgressLines()), plan.fps)
    except OSError as exc:
        raise write_error(exc, video, "pass --video PATH to write it elsewhere") from None
    w, h = plan.size
    shown = (f"{plan.pairs} of {counted(plan.total, 'pair')}" if plan.pairs < plan.total
             else counted(plan.total, "pair"))
    again = (f": its {counted(len(plan.shots), 'frame')} played {plan.loops} times to last at "
             f"least {MIN_SECONDS:g} s" if plan.loops > 1 else "")
    click.echo(f"Video of {shown} written to {video}: {counted(count, 'frame')} of {w}x{h} at "
               f"{plan.fps:g} fps ({count / plan.fps:.1f} s{again})")
    _left_out(plan.unreadable)


class ProgressLines:
    """``progress(done, count)`` for a long video: a line on stderr every ``every`` seconds of
    work (none for a video made sooner), saying how many frames are composed and encoded."""

    def __init__(self, every: float = 5.0, clock=time.monotonic):
        self.every, self.clock = every, clock
        self.start = self.last = clock()

    def __call__(self, done: int, count: int) -> None:
        now = self.clock()
        if now - self.last >= self.every and done < count:
            self.last = now
            click.echo(f"  video: {done} of {counted(count, 'frame')} ({now - self.start:.0f} s)",
                       err=True)
