"""Options shared by several commands, declared once, and how library parameters are spelled."""

from __future__ import annotations

import dataclasses
import functools
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import click

from weathergen.datasets import DATASETS, default_dataset, load_scene_scales, open_dataset
from weathergen.datasets.common import WORLD_UP_CHOICES
from weathergen.errors import ConfigError
from weathergen.geometry import up_direction
from weathergen.models import INPUT_CONVENTIONS, PRECISIONS, resolve_network


#: Where the group keeps the command line it was given (``ctx.meta``), for manifests.
ARGV_KEY = "weathergen.argv"

#: Library parameters whose command-line option has another name; the others are ``--name``.
OPTIONS = {"particles_from": "--particles", "config_name": "--config", "fmt": "--format",
           "overrides": "--set", "pass_": "--pass"}


def option_of(parameter: str) -> str:
    """The command-line option of a library parameter (``pass_name`` -> ``--pass-name``)."""
    return OPTIONS.get(parameter, "--" + parameter.replace("_", "-"))


# -- options of every command that runs a job -------------------------------------------------

def device_option(func):
    """``--device``: where the job runs."""
    return click.option("--device", default="cpu", show_default=True,
                        help="cpu, cuda or cuda:N.")(func)


def quiet_option(func):
    """``--quiet``/``-q``: print nothing but errors."""
    return click.option("--quiet", "-q", is_flag=True, help="Print nothing but errors.")(func)


def seed_option(help: str):
    """``--seed``: the run seed (default 0); ``help`` says what it seeds."""
    return click.option("--seed", type=int, default=0, show_default=True, help=help)


def out_option(default: str):
    """``--out``: the output folder; ``default`` says where it goes without one."""
    return click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
                        help=f"Output folder. Default: {default}.")


def resume_option(help: str):
    """``--resume``: finish an interrupted run; ``help`` says what is skipped."""
    return click.option("--resume", is_flag=True, help=help)


def _compat(help: str):
    """``--compat paper|reference`` (unset: paper) with the command's own ``help``."""
    return click.option("--compat", type=click.Choice(("paper", "reference")), default=None,
                        help=help)


def compat_option(func):
    """``--compat``: the paper's attack terms (default) or the research code's."""
    return _compat(
        help="paper (default): the attack of the paper's equations and tables; reference: the "
             "authors' research code where it departs from them (gradients accumulated over the "
             "steps, occlusion detached, penalty over the squared frame-1 depth, homogeneous "
             "offsets, transparency capped at the preset's, its figures, its blending of "
             "alpha-blended motion blur one sample after another, its particles' stamps, and "
             "its frame and "
             "scaling of Sintel: --scene-scales research unless given, the camera translation "
             "zeroed in the scaled scenes), to reproduce its published tables. See "
             "docs/attack.md.")(func)


def render_compat_option(func):
    """``--compat`` of ``render``: the dataset in the research code's frame and scaling."""
    return _compat(
        help="reference: open the dataset in the frame and scaling of the paper's research code "
             "(its per-scene table, --scene-scales research, unless given; the camera translation "
             "zeroed in the scenes it scales), where the paper's published weather was placed, "
             "and blend alpha-blended motion blur one sample after another and make sampled "
             "particles' stamps as that code does (docs/render.md), so --particles SET draws the "
             "research code's render of it. Default: paper (the dataset as the other options "
             "open it, weathergen's blending and stamps).")(func)


def overwrite_option(help: str):
    """``--overwrite``: redo or replace what a folder holds; ``help`` says what."""
    return click.option("--overwrite", is_flag=True, help=help)


# -- settings records: options that travel together ---------------------------------------------

@dataclass(frozen=True)
class RunOptions:
    """Where a job's pairs are computed and what it does with an earlier run's output: the
    options every command that runs a job over a dataset takes (``--device``, ``--executor``,
    ``--ray-address``, ``--batch-size``, ``--resume``, ``--overwrite``), named as the jobs'
    fields."""

    device: str = "cpu"
    executor: str = "local"
    ray_address: Optional[str] = "auto"
    batch_size: Optional[int] = None
    resume: bool = False
    overwrite: bool = False


@dataclass(frozen=True)
class ModelOptions:
    """The flow network and how it runs: the options of :func:`model_options` (``--model``, the
    name as given, ``--checkpoint``, ``--iters``, ``--download``, ``--model-input``, ``--amp``,
    ``--precision``), taken by every command that runs one network."""

    model: str = "raft"
    checkpoint: Optional[str] = None
    iters: Optional[int] = None
    download: bool = False
    model_input: Optional[str] = None
    amp: Optional[bool] = None
    precision: Optional[str] = None


def gathered(name: str, record: type):
    """Decorator (right above the command's ``def``): the command's options named as the fields
    of the dataclass ``record`` come in as one ``record`` under the parameter ``name``."""
    fields = [f.name for f in dataclasses.fields(record)]

    def wrap(command):
        @functools.wraps(command)
        def call(**options):
            values = {key: options.pop(key) for key in fields}
            return command(**options, **{name: record(**values)})
        return call
    return wrap


# -- option groups --------------------------------------------------------------------------

def attack_steps(ctx, param, value):
    """Callback of ``--steps`` (and ``--lp-steps``): an attack takes at least one step.

    With none, the "adversarial" result would be the starting point itself (the random weather,
    or the clean frames of an Lp attack), written under the attack's name.
    """
    if value is not None and value < 1:
        clean = "the clean frames, from which an Lp attack starts"
        weather = "random weather: measure that with `weathergen render` and `weathergen evaluate`"
        method = ctx.params.get("method")      # attack --method, when click has read it already
        if param.name == "lp_steps" or method not in (None, "weather"):
            start = clean
        elif method is None and any(p.name == "method" for p in ctx.command.params):
            start = ("random weather, or the clean frames for an Lp attack; measure random weather "
                     "with `weathergen render` and `weathergen evaluate`")
        else:
            start = weather
        raise click.BadParameter(
            f"{value}: an attack takes at least one step; with none its 'adversarial' result "
            f"would be the unoptimised start ({start})")
    return value


def _world_up_option(ctx, param, value):
    """Validate --world-up (an axis name or a direction X,Y,Z); keep the text as given."""
    if value is None:
        return None
    try:
        up_direction(value)
    except ConfigError as exc:
        raise click.BadParameter(str(exc).split(": ", 1)[-1]) from None
    return value.strip()


def dataset_options(func):
    """Add the dataset-selection options; the command receives ``dataset`` (an opened Dataset)."""

    @click.option("--dataset", "dataset_name", type=click.Choice(sorted(DATASETS)), default=None,
                  help="Dataset format. Default: 'demo' (the bundled scene) without --root, "
                       "'sintel' with --root.")
    @click.option("--root", type=click.Path(path_type=str), default=None,
                  help="Folder the dataset is stored in. Default: the bundled demo scene.")
    @click.option("--split", default="training", show_default=True,
                  help="Dataset split (Sintel: training/test; KITTI: training/testing; "
                       "Spring: train/test, training/testing accepted).")
    @click.option("--pass", "pass_", default="clean", show_default=True,
                  help="Rendering pass (Sintel: clean or final; the other datasets have one).")
    @click.option("--scenes", default=None, metavar="A,B,...",
                  help="Only these scenes (comma-separated). Default: all.")
    @click.option("--from-scene", default=None, metavar="NAME",
                  help="Only scenes from this one on (in sorted order). Default: from the first.")
    @click.option("--frames-per-scene", type=click.IntRange(min=1), default=None,
                  help="At most this many pairs per scene; 5 gives the paper's Sintel-tr115. "
                       "Default: all.")
    @click.option("--first-frame", type=click.IntRange(min=0), default=None,
                  help="Start each scene at this frame number (as in the file names). "
                       "Default: its first frame.")
    @click.option("--depth-scale", type=float, default=1.0, show_default=True,
                  help="Multiply all depth (and camera translation) by this factor.")
    @click.option("--scene-scales", type=click.Path(dir_okay=False, path_type=str), default=None,
                  help="TOML/JSON table of per-scene depth factors, applied on top of --depth-scale; "
                       "'research': the paper's research code's table (bundled). Default: none "
                       "(every scene 1.0).")
    @click.option("--camera-translation/--no-camera-translation", default=True, show_default=True,
                  help="Keep the camera translation between the two frames (or zero it).")
    @click.option("--no-translation-in-scaled-scenes", "unscaled_translation", is_flag=True,
                  help="Zero the camera translation only in the scenes --depth-scale and "
                       "--scene-scales scale (factor not 1), as the paper's research code does "
                       "(with --scene-scales research: its frame and scaling).")
    @click.option("--far-depth", type=click.FloatRange(min=0, min_open=True), default=None,
                  help="kitti, spring, custom: depth (dataset units, before --depth-scale) given to "
                       "the sky (and to unknown depth with --fill-gaps 0). Default: 1000.")
    @click.option("--world-up", metavar="|".join(WORLD_UP_CHOICES) + "|X,Y,Z", default=None,
                  callback=_world_up_option,
                  help="Axis of the dataset's world that points up (weather falls the other way), "
                       "or the up direction X,Y,Z in world coordinates for a world that is not "
                       "level. Default: the dataset's (demo +z, kitti -y, others auto: the world "
                       "axis nearest to the cameras' up direction).")
    @reader_options
    @functools.wraps(func)
    def wrapper(*args, dataset_name, root, split, pass_, scenes, from_scene, frames_per_scene,
                first_frame, **kwargs):
        name = dataset_name or default_dataset(root)
        options = _reader_keywords(name, kwargs)
        kwargs["dataset"] = open_dataset(
            name, root, split=split, pass_=pass_,
            scenes=[s.strip() for s in scenes.split(",") if s.strip()] if scenes else None,
            from_scene=from_scene, frames_per_scene=frames_per_scene, first_frame=first_frame,
            **options)
        return func(*args, **kwargs)

    return wrapper


def _reader_keywords(name: str, given: dict) -> dict:
    """The keywords for reader ``name`` that the depth, camera and reader options ask for, taken
    out of ``given`` (the command's keyword arguments); an option that does not apply is refused."""
    reader = DATASETS[name]
    camera_translation = given.pop("camera_translation")
    unscaled_translation = given.pop("unscaled_translation")
    if unscaled_translation and not camera_translation:
        raise click.UsageError("--no-translation-in-scaled-scenes keeps the translation of "
                               "the unscaled scenes; --no-camera-translation zeroes every one: "
                               "give one of them")
    translation = "unscaled" if unscaled_translation else camera_translation
    scene_scales = given.pop("scene_scales")
    options = dict(depth_scale=given.pop("depth_scale"), camera_translation=translation,
                   scene_scales=load_scene_scales(scene_scales) if scene_scales else None,
                   world_up=given.pop("world_up"))
    for flag, keyword in READER_OPTIONS.items():
        value = given.pop(flag)
        if value is not None:
            if keyword not in reader.options:
                names = [n for n, cls in DATASETS.items() if keyword in cls.options]
                raise click.UsageError(f"--{flag.replace('_', '-')} applies to "
                                       f"{', '.join(names)} only, not to {name}")
            options[keyword] = value
    far_depth = given.pop("far_depth")
    if far_depth is not None:
        if reader.dense_depth:
            raise click.UsageError(f"--far-depth does not apply to {name}: its depth is dense")
        options["far_depth"] = far_depth
    return options


#: Options of one reader or two: option name -> the reader's keyword. Which readers take it is
#: theirs to say (:attr:`~weathergen.datasets.Dataset.options`).
READER_OPTIONS = {
    "fit_threshold": "fit_threshold_px",
    "fit_min_inliers": "fit_min_inlier_fraction",
    "fit_min_points": "fit_min_points",
    "fit_max_rms": "fit_max_rms_px",
    "object_map": "use_object_map",
    "frame_pattern": "frame_pattern",
    "min_valid_depth": "min_valid_depth",
    "fill_gaps": "max_gap_px",
}


def reader_options(func):
    """The options of :data:`READER_OPTIONS` (None when not given)."""
    for option in reversed((
        click.option("--fit-threshold", type=float, default=None, metavar="PX",
                     help="kitti: a correspondence agrees with the camera motion within this "
                          "reprojection error. Default: 2."),
        click.option("--fit-min-inliers", type=float, default=None, metavar="FRACTION",
                     help="kitti: refuse a pair whose camera motion fewer than this fraction of "
                          "the correspondences agree with. Default: 0.5."),
        click.option("--fit-min-points", type=int, default=None, metavar="N",
                     help="kitti: refuse a pair with fewer correspondences. Default: 200."),
        click.option("--fit-max-rms", type=float, default=None, metavar="PX",
                     help="kitti: refuse a pair whose inliers' RMS reprojection error is larger. "
                          "Default: 1.5."),
        click.option("--object-map/--no-object-map", default=None,
                     help="kitti: leave out the moving objects of obj_map from the camera-motion "
                          "fit. Default: yes where the file exists."),
        click.option("--frame-pattern", default=None, metavar="GLOB",
                     help="custom: the frames are the files of frames/ matching this pattern "
                          "(e.g. '*_left.png'). Default: every image file there."),
        click.option("--min-valid-depth", type=float, default=None, metavar="FRACTION",
                     help="custom: warn about frames with a smaller fraction of valid depth. "
                          "Default: 0.5."),
        click.option("--fill-gaps", type=click.FloatRange(min=0), default=None, metavar="PX",
                     help="kitti, custom: fill gaps in the depth up to this distance from a "
                          "measured pixel (guided by the frame's colours) and complete larger "
                          "regions that are not sky; 0 fills nothing (unknown depth, at the far "
                          "depth). Default: 24."),
    )):
        func = option(func)
    return func


#: ``--amp/--no-amp``: mixed precision of the network (CUDA only); shared with ``benchmark``.
amp_option = click.option(
    "--amp/--no-amp", default=None,
    help="Run the network in its authors' mixed precision (CUDA autocast; RAFT, RAFT-small, "
         "GMA). Default: as the paper's configuration, on for GMA and off for the others; on "
         "the CPU always off (--amp there is an error).")


#: ``--precision``: the network's arithmetic; shared with ``benchmark``.
precision_option = click.option(
    "--precision", type=click.Choice(PRECISIONS), default=None,
    help="The network's arithmetic: float32; tf32 (CUDA tensor cores); bf16 or fp16 (autocast; "
         "correlation volumes, softmax, warping and the loss stay float32). A precision whose "
         "flow differs too much from float32's is refused for that network (docs/models.md). "
         "Default: as --amp (fp16 where it is on, else float32). Not with --amp/--no-amp.")


def early_stop_option(func):
    """``--early-stop WINDOW:TOL``: end a pair's weather attack once its loss has converged."""
    return click.option(
        "--early-stop", default=None, metavar="WINDOW:TOL",
        help="End a pair's weather attack when its best loss over the last WINDOW steps is not "
             "lower than before them by more than TOL (relative, e.g. 50:0.001); the best step "
             "is kept. Default: every step (the paper's setting; --compat reference allows no "
             "other).")(func)


def model_options(func):
    """Add the flow-network options: ``model``, ``checkpoint``, ``iters``, ``download``,
    ``model_input``, ``amp``, ``precision`` (gathered as :class:`ModelOptions`)."""
    for option in reversed((
        click.option("--model", default="raft", show_default=True,
                     help="Flow network or checkpoint name (raft, raft-small, gma, flowformer, "
                          "raft-things, ...; `weathergen models` lists them), an installed "
                          "network's name, or a network of your own: FILE.py:NAME or "
                          "package.module:NAME (see docs/models.md)."),
        click.option("--checkpoint", default=None,
                     help="Checkpoint file or name. Default: the model's own, from the user cache "
                          "(a network of your own: none, its code gives the weights)."),
        click.option("--iters", type=click.IntRange(min=1), default=None,
                     help="Refinement iterations of recurrent networks. Default: the network's "
                          "own (RAFT 12, GMA 6, FlowFormer 32)."),
        click.option("--download", is_flag=True,
                     help="Fetch a named checkpoint that is missing from the cache (needs a network)."),
        click.option("--model-input", type=click.Choice(list(INPUT_CONVENTIONS)), default=None, metavar="CONV",
                     help="The input convention of a plain module of your own that declares none "
                          "(input_range, channel_order): rgb, bgr ([0, 1]), rgb255, bgr255 "
                          "([0, 255]). Default: rgb, said in a note."),
        amp_option,
        precision_option,
    )):
        func = option(func)
    return func


def resolve_model(name: str, model_input=None):
    """The network ``name`` resolved once (:func:`~weathergen.models.resolve_network`); a plain
    module that declares no input convention gets one note on stderr."""
    network = resolve_network(name, model_input)
    if network.note():
        click.echo(f"Note: {network.note()}", err=True)
    return network


def executor_options(func):
    """``--executor`` and ``--ray-address``: where the pairs are computed."""
    for option in reversed((
        click.option("--executor", type=click.Choice(["local", "ray"]), default="local",
                     show_default=True,
                     help="Compute pairs in this process (local) or as tasks on a Ray cluster "
                          "(ray; needs pip install 'weathergen[ray]')."),
        click.option("--ray-address", default="auto", show_default=True, metavar="auto|local|HOST:PORT",
                     help="With --executor ray: the cluster to join (auto: the one started on "
                          "this machine by `ray start`; local: a private one for this run)."),
    )):
        func = option(func)
    return func


# -- exit codes, stated in every command's --help ------------------------------------------------

#: Exit 2: what every command says about it.
BAD_INPUT = ("2", "bad options or input, or a file that cannot be written: one line on stderr, "
                  "no file left half-written")
#: Exit 130 / 143 of a command that writes nothing a later run needs.
STOPPED = ("130, 143", "stopped by Ctrl-C / SIGTERM (one line; no file left half-written)")


def exit_codes(*codes: tuple[str, str]) -> str:
    """The epilog of a command's ``--help``: its exit codes, one per line (``(code, meaning)``)."""
    width = max(len(code) for code, _ in codes)
    lines = []
    for code, text in codes:
        wrapped = textwrap.wrap(text, 76 - width) or [""]
        lines += [f"  {code:<{width}}  {wrapped[0]}", *(f"  {'':<{width}}  {w}" for w in wrapped[1:])]
    return "\b\nExit codes:\n" + "\n".join(lines)


def job_exit_codes(again: str = "--resume finishes the run", every_failed: int = 2) -> str:
    """The exit codes of ``render`` and ``attack`` (``again``: how a stopped run is finished;
    ``every_failed``: the code of a run where every selected pair failed, 2 for ``render``, 1 for
    ``attack``, which records the failures in its manifest)."""
    if every_failed == 2:
        failed = ("1", "some pairs failed (each named on stderr, recorded in the manifest); the "
                       "others were written")
        bad = ("2", "bad options or input, a full disk or unwritable folder, or every pair failed "
                    "(one line; the finished pairs are recorded, a folder the run created and "
                    "wrote nothing into is removed)")
    else:
        failed = ("1", "some or all pairs failed (each named on stderr, recorded in the manifest); "
                       "the others were written")
        bad = ("2", "bad options or input, a full disk or unwritable folder (one line; the "
                    "finished pairs are recorded)")
    return exit_codes(
        ("0", "every selected pair written (or already complete); warnings may be printed"),
        failed, bad,
        ("130, 143", f"stopped by Ctrl-C / SIGTERM: the finished pairs are kept and recorded; "
                     f"{again}"))
