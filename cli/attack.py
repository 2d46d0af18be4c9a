"""``weathergen attack``: optimise weather against a flow network, pair by pair."""

from __future__ import annotations

import sys
from contextlib import nullcontext
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Optional

import click
import torch
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from weathergen.attack import (ATTACK_CONFIGS, DEFAULT_STEPS, FIELD_LR, LP_METHODS, PCFA_OPTIMIZERS,
                               AttackJob, EarlyStop, lp_pass_name, parse_target, plan_lp,
                               run_attack)
from weathergen.attack.plan import attack_pass_name, default_attack_out, plan_attack
from weathergen.attack.record import settings_text
from weathergen.datasets import in_research_frame
from weathergen.engine import parse_set_options, resolve_device
from weathergen.errors import ConfigError
from weathergen.execution import RunClock, check_executor
from weathergen.words import counted

from .options import (ModelOptions, RunOptions, attack_steps, compat_option, dataset_options,
                      device_option, early_stop_option, executor_options, gathered, job_exit_codes,
                      model_options, out_option, overwrite_option, quiet_option, resolve_model,
                      resume_option, seed_option)
from .stopping import exit_interrupted, terminate_as_interrupt


def _fmt(value, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


#: Under ``--compat reference`` the adversarial AEE is the research code's figure, not AEE(f, f̌).
REFERENCE_FIGURE = ("* --compat reference: the research code's figure, the best step's flow "
                    "against the random weather's flow (float frames; docs/attack.md)")


def summary_table(title: str, summary: dict, what: str = "weather", compat: str = "paper") -> Table:
    """Mean figures over the attacked pairs (pixels): one row per measure, one column per input.
    Under ``compat="reference"`` the adversarial AEE is marked and explained in a caption."""
    reference = compat == "reference"
    table = Table(title=title, caption=REFERENCE_FIGURE if reference else None)
    table.add_column(f"mean over {counted(summary['pairs'], 'pair')}")
    for col in ("clean", f"random {what}", f"adversarial {what}"):
        table.add_column(col, justify="right")
    table.add_row("AEE(f, f̌)", "0", _fmt(summary["aee_random"]),
                  _fmt(summary["aee_adversarial"]) + (" *" if reference else ""))
    if summary.get("per_pair_aee_adversarial") is not None:     # --sequence
        table.add_row("AEE(f, f̌), each pair attacked alone", "", _fmt(summary["aee_random"]),
                      _fmt(summary["per_pair_aee_adversarial"]))
    if summary.get("second_aee_random") is not None:            # --sequence --stereo
        table.add_row("AEE(f, f̌), second camera", "", _fmt(summary["second_aee_random"]),
                      _fmt(summary["second_aee_adversarial"]))
    table.add_row("AEE(f̌, target)", "", _fmt(summary["target_initial"]),
                  _fmt(summary["target_adversarial"]))
    table.add_row("EPE vs ground truth", _fmt(summary["epe_benign"]), _fmt(summary["epe_random"]),
                  _fmt(summary["epe_adversarial"]))
    for row in region_rows(summary):
        table.add_row(row[0], "", "", row[1])
    return table


def scene_table(summary: dict) -> Table:
    """A sequence attack's AEE(f, f̌) per scene: random weather, one adversarial weather for the
    scene, and each pair attacked alone (pixels)."""
    table = Table(title="AEE(f, f̌) per scene (pixels)")
    for col in ("scene", "pairs", "random", "one weather", "pairs alone"):
        table.add_column(col, justify="left" if col == "scene" else "right")
    for scene, f in summary["scenes"].items():
        table.add_row(scene, str(f["pairs"]), _fmt(f["aee_random"]), _fmt(f["aee_adversarial"]),
                      _fmt(f["per_pair_aee_adversarial"]))
    return table


def region_rows(summary: dict) -> list[tuple[str, str]]:
    """The figures by region and the outlier rates of a summary as (label, value) rows."""
    def pair(a, b):
        return f"{_fmt(summary[a])} / {_fmt(summary[b])}"

    coverage = summary.get("weather_coverage")
    covers = "" if coverage is None else f" ({coverage:.1f} % of pixels)"
    return [(f"AEE(f, f̌) weather{covers} / clear pixels", pair("aee_weather_px", "aee_clear_px")),
            ("EPE weather / clear pixels", pair("epe_weather_px", "epe_clear_px")),
            ("Fl-all; outliers > 1, 3, 5 px (%)",
             f"{_fmt(summary['fl_all'], 2)}; " + ", ".join(
                 _fmt(summary[f"outliers_{n}px"], 2) for n in (1, 3, 5))),
            ("robust EPE; Fl, 1px (%) vs clean flow (RobustSpring)",
             f"{_fmt(summary.get('robust_epe'))}; {_fmt(summary.get('robust_fl'), 2)}, "
             f"{_fmt(summary.get('robust_1px'), 2)}")]


@dataclass(frozen=True)
class AttackRequest:
    """What to attack and how: the options of ``attack`` that its plan
    (:func:`~weathergen.attack.plan_attack`, :func:`~weathergen.attack.plan_lp`) turns into the
    attack's settings, named as the command's parameters."""

    method: str
    epsilon: Optional[float]
    optimizer: Optional[str]
    config_name: Optional[str]
    preset: Optional[str]
    set_items: tuple
    particles_dir: Optional[Path]
    steps: Optional[int]
    optimize: Optional[str]
    optimize_layer: Optional[str]
    lr: Optional[float]
    group_lr: tuple
    sequence: bool
    stereo: bool
    alpha1: float
    alpha2: float
    target_text: str
    occlusion_gradient: Optional[bool]
    compat: Optional[str]
    early_stop: Optional[str]
    gradient_checkpointing: bool


@click.command(epilog=job_exit_codes(every_failed=1))
@dataset_options
@model_options
@click.option("--method", type=click.Choice(("weather",) + LP_METHODS), default="weather",
              show_default=True,
              help="weather: optimise weather particles; pcfa: the L2 baseline PCFA; ifgsm: the "
                   "L-infinity baseline I-FGSM (both perturb the frames themselves).")
@click.option("--epsilon", type=float, default=None,
              help="Bound of an Lp attack: pcfa the normalised L2 norm over both frames, ifgsm "
                   "the L-infinity norm. Default 5e-3 (the paper's).")
@click.option("--optimizer", type=click.Choice(PCFA_OPTIMIZERS), default=None,
              help="PCFA's optimiser: lbfgs (default; the PCFA paper's, which the paper ran: 20 "
                   "steps of up to 10 L-BFGS iterations) or adam (one network pass per step, "
                   "every step projected into the bound).")
@click.option("--config", "config_name", default=None, metavar="NAME",
              help=f"An attack configuration of the paper's supplement ({', '.join(ATTACK_CONFIGS)}): "
                   "sets preset, --optimize, --lr and the occlusion gradient; explicit options win.")
@click.option("--preset", default=None,
              help="Weather preset the particles are sampled from; presets joined by + "
                   "(e.g. snow+fog-light) are attacked together, see --optimize-layer. "
                   "Default: the --config's preset, else snow.")
@click.option("--set", "set_items", multiple=True, metavar="KEY=VALUE",
              help="Override one preset key (repeatable), e.g. --set count=500.")
@click.option("--particles", "particles_dir", type=click.Path(file_okay=False, path_type=Path),
              default=None, help="Start from the particles of an earlier render (or attack) "
                                 "output instead of sampling.")
@click.option("--steps", type=int, default=None, callback=attack_steps,
              help=f"Optimisation steps per pair (at least 1). Default: {DEFAULT_STEPS} (weather), 20 (pcfa), "
                   "25 (ifgsm).")
@click.option("--optimize", default=None, metavar="A,B,...",
              help="Variables to optimise: offset1, offset2, color, transparency; density and "
                   "airlight of a weather field's atmosphere (fog-*, mist, rain-*, snow-*); or "
                   "'all'. Default: the --config's, else the four particle variables (fog: all "
                   "but offset2), and density and airlight where the preset has an atmosphere; "
                   "--sequence leaves out offset2.")
@click.option("--optimize-layer", "optimize_layer", default=None, metavar="NAME[,NAME]|all",
              help="Combined presets (layers joined by +): the layers whose particles are "
                   "optimised, by name (e.g. fog-light); the others stay as sampled. "
                   "Default: all.")
@click.option("--lr", type=float, default=None,
              help="Adam learning rate of every variable group (see --group-lr for the "
                   "defaults); pcfa: L-BFGS step size 1, Adam 1e-3; for ifgsm the step size, "
                   "default epsilon / steps.")
@click.option("--group-lr", "group_lr", multiple=True, metavar="GROUP=RATE",
              help="Adam learning rate of one variable group (repeatable; wins over --lr): "
                   "positions (offset1, offset2), color, transparency, density, airlight. "
                   "Defaults: the paper's presets' particles 1e-5 when an offset is optimised, "
                   "else 1e-3 (all three groups); weather fields (snow-*, rain-*, fog-*, mist "
                   f"and their combinations) {', '.join(f'{g} {r:g}' for g, r in FIELD_LR.items())}, "
                   "whose density and airlight rates hold for every preset's atmosphere. The "
                   "manifest records the rates used.")
@click.option("--sequence", is_flag=True,
              help="One weather for each whole scene (weather-field presets): the field's "
                   "particles in the world (offset1, colour, transparency) and its atmosphere "
                   "(density, airlight), optimised "
                   "against every pair of the scene at once, so every frame shows the same "
                   "weather; each pair is also attacked alone with the same settings, for "
                   "comparison (per_pair_* figures).")
@click.option("--stereo", is_flag=True,
              help="With --sequence: against the dataset's second (right) camera too, as "
                   "`render --stereo` draws it (second_aee_* figures, float frames).")
@click.option("--alpha1", type=float, default=1000.0, show_default=True,
              help="Weight of the frame-1 offset penalty.")
@click.option("--alpha2", type=float, default=1000.0, show_default=True,
              help="Weight of the frame-2 offset penalty.")
@click.option("--target", "target_text", default="zero", show_default=True,
              help="Target flow: zero, negative (minus the benign flow), U,V (constant, pixels) "
                   "or a .flo file.")
@click.option("--occlusion-gradient/--no-occlusion-gradient", default=None,
              help="Soften occlusion (beta 30 instead of 250) so gradients pass through it. "
                   "Default: on for fog, off otherwise.")
@compat_option
@early_stop_option
@click.option("--gradient-checkpointing", is_flag=True,
              help="Recompute the network's refinement steps in the backward pass (less memory, "
                   "more time).")
@out_option("out/attack-<config or preset>")
@seed_option("Run seed; each pair's particles are seeded as by `weathergen render`.")
@device_option
@click.option("--batch-size", type=click.IntRange(min=1), default=1, show_default=True,
              help="Pairs of one size optimised together, in one forward and backward pass per "
                   "step (results as pair by pair, up to floating-point rounding).")
@executor_options
@resume_option("Finish an interrupted run: skip finished pairs.")
@overwrite_option("Redo every pair, even in a folder that holds one.")
@quiet_option
@gathered("net", ModelOptions)
@gathered("run", RunOptions)
@gathered("request", AttackRequest)
def attack(dataset, out, seed, quiet, net: ModelOptions, run: RunOptions, request: AttackRequest):
    """Optimise weather particles so that a flow network's output moves towards a target.

    With no option it attacks RAFT with snow on the bundled demo scene into out/attack-snow.
    Writes adversarial frames, best particles (re-render them with `weathergen render
    --particles OUT`), flows, a per-step log, manifest.json and summary.json.
    """
    check_executor(run.executor)
    if run.executor == "local":       # a Ray driver need not have the workers' devices
        resolve_device(run.device)
    target = parse_target(request.target_text)
    model = resolve_model(net.model, net.model_input)
    if request.method != "weather":
        label, steps, fields = _lp_attack(dataset, request)
    else:
        dataset, label, steps, fields = _weather_attack(dataset, request)
    job = AttackJob(dataset=dataset, out=out or default_attack_out(label), model=model,
                    checkpoint=net.checkpoint, iters=net.iters, download=net.download,
                    amp=net.amp, precision=net.precision, target=target, seed=seed,
                    gradient_checkpointing=request.gradient_checkpointing,
                    command=["weathergen", *sys.argv[1:]], threads=torch.get_num_threads(),
                    **asdict(run), **fields)
    _run(job, model.label, label, target, steps, job.out, quiet)


def _lp_attack(dataset, request: AttackRequest) -> tuple[str, int, dict]:
    """``(label, steps, the job's fields)`` of an Lp baseline; refuses the weather's options."""
    r = request
    if r.group_lr or r.sequence or r.stereo:
        which = "group_lr" if r.group_lr else "sequence" if r.sequence else "stereo"
        raise ConfigError(f"${{{which}}} applies to --method weather only")
    if r.early_stop is not None:
        raise ConfigError("${early_stop} applies to the weather attack only")
    lp = plan_lp(r.method, r.epsilon, r.steps, r.lr, r.optimizer, config_name=r.config_name,
                 preset=r.preset, overrides=tuple(r.set_items), particles_from=r.particles_dir,
                 optimize=r.optimize, optimize_layer=r.optimize_layer,
                 occlusion_gradient=r.occlusion_gradient,
                 compat=None if r.compat in (None, "paper") else r.compat)
    return r.method, lp.steps, dict(preset=None, preset_name=r.method, settings=None, lp=lp,
                                    pass_name=lp_pass_name(r.method, dataset.selection.pass_))


def _weather_attack(dataset, request: AttackRequest) -> tuple:
    """``(dataset, label, steps, the job's fields)`` of the weather attack, the dataset in the
    research code's frame under ``--compat reference``; refuses the Lp baselines' options."""
    r = request
    if r.epsilon is not None:
        raise ConfigError("${epsilon} applies to --method pcfa or ifgsm only")
    if r.optimizer is not None:
        raise ConfigError("${optimizer} applies to --method pcfa only")
    early_stop = None if r.early_stop is None else EarlyStop.parse(r.early_stop)
    steps = DEFAULT_STEPS if r.steps is None else r.steps
    if r.compat == "reference":       # the research code's frame and scaling too
        dataset = in_research_frame(dataset)
    plan = plan_attack(r.config_name, r.preset, parse_set_options(r.set_items), r.particles_dir,
                       optimize=r.optimize, lr=r.lr, occlusion_gradient=r.occlusion_gradient,
                       steps=steps, alpha1=r.alpha1, alpha2=r.alpha2, compat=r.compat or "paper",
                       layers=r.optimize_layer, group_lr=r.group_lr, sequence=r.sequence)
    return dataset, plan.label, steps, dict(
        preset=plan.preset, preset_name=plan.preset_name,
        settings=replace(plan.settings, early_stop=early_stop), particles_from=r.particles_dir,
        config_name=r.config_name,
        pass_name=attack_pass_name(plan.preset_name, dataset.selection.pass_),
        sequence=r.sequence, stereo=r.stereo)


class _Reporter:
    """What a run prints as it goes: a progress bar on a terminal, else a line per written pair
    and every 50th step (nothing with ``quiet``); warnings and failures on stderr."""

    def __init__(self, steps: int, versus: str, quiet: bool):
        self.console, self.err = Console(), Console(stderr=True)
        self.total_steps, self.versus, self.quiet = int(steps), versus, quiet
        self.written, self.failed, self.clock, self.task = 0, [], None, None
        self.progress = (Progress(TextColumn("[bold]{task.description}"), BarColumn(bar_width=12),
                                  MofNCompleteColumn(), TimeElapsedColumn(),
                                  TextColumn("{task.fields[status]}"), console=self.console)
                         if self.console.is_terminal and not quiet else None)

    def on_start(self, n):
        self.clock = RunClock(n)
        if self.progress is not None:
            self.task = self.progress.add_task("attack", total=n * (self.total_steps + 1),
                                               status="")

    def on_step(self, pair_name, rec):
        # scene/frame is enough to tell pairs apart in one run, and keeps the line short
        short = "/".join(pair_name.split("/")[-2:])
        text = (f"{self.clock.describe()}; {short} step {rec.step}/{self.total_steps}"
                f"  loss {rec.loss:.4f}  best distance {rec.best_distance:.4f}")
        if self.progress is not None:
            self.progress.update(self.task, advance=1, status=text)
        elif not self.quiet and (rec.step % 50 == 0 or rec.step == self.total_steps):
            self.console.print(text, highlight=False, soft_wrap=True)

    @staticmethod
    def on_note(text):
        click.echo(f"Note: {text}", err=True)

    def on_pair_done(self, report):
        self.clock.add(computed=report.status == "written")
        self.written += report.status == "written"
        if report.summary is not None and report.summary.nothing_visible \
                and report.status == "written":
            self._warn(f"[yellow]warning[/yellow] {report.pair}: no particle is visible, so "
                       f"nothing could be optimised; the random weather was kept")
        for text in report.warnings:       # attacked, but the input looks wrong
            self._warn(f"[yellow]warning[/yellow] {report.pair}: {text}")
        if report.status == "failed":
            self.failed.append(report)
            self._warn(f"[red]failed[/red] {report.pair}: {report.message}")
        if self.progress is not None:
            # counts the steps a pair did not report (skipped, failed, frozen, run by Ray)
            self.progress.update(self.task, completed=self.clock.done * (self.total_steps + 1),
                                 status=self.clock.describe())
        if not self.quiet and self.progress is None and report.status != "failed":
            s = report.summary      # a sequence attack's: the pair attacked alone too
            alone = ("" if s.per_pair_aee_adversarial is None else
                     f" (the pair attacked alone: {s.per_pair_aee_adversarial:.3f})")
            self.console.print(f"[{self.clock.describe()}] {report.pair} {report.status}: AEE(f, f̌) "
                               f"random {s.aee_random:.3f} -> adversarial{self.versus} "
                               f"{s.aee_adversarial:.3f}{alone}, distance to target "
                               f"{s.target_initial:.3f} -> {s.target_adversarial:.3f}",
                               highlight=False, soft_wrap=True)

    def _warn(self, text: str) -> None:
        """One unwrapped line on stderr (above the progress bar), so paths stay whole."""
        (self.progress.console if self.progress else self.err).print(text, highlight=False,
                                                                     soft_wrap=True)


def _run(job, model, label, target, steps, out, quiet):
    compat_mode = "paper" if job.lp is not None else job.settings.compat
    versus = " (vs the random weather's flow)" if compat_mode == "reference" else ""
    shown = _Reporter(steps, versus, quiet)
    stopped_by = None
    try:
        with terminate_as_interrupt() as stopped_by:
            with shown.progress if shown.progress is not None else nullcontext():
                summary = run_attack(job, shown.on_start, shown.on_step, shown.on_pair_done,
                                     shown.on_note)
    except KeyboardInterrupt:
        exit_interrupted(shown.written, stopped_by)
    if not quiet:
        _print_summary(shown.console, job, f"{model}, {label}", target, out, summary,
                       compat_mode)
    if shown.failed:
        shown.err.print(f"[red]{counted(len(shown.failed), 'pair')} failed[/red]; see the "
                        f"messages above.")
        sys.exit(1)


def _print_summary(console, job, what: str, target, out, summary: dict, compat_mode: str):
    """The run's mean figures, settings, per-scene figures (a sequence attack) and output."""
    mode = "" if compat_mode == "paper" else f", compat {compat_mode}"
    console.print(summary_table(f"weathergen attack: {what}, target "
                                f"{target.describe()}{mode} (pixels)", summary,
                                "weather" if job.lp is None else "perturbation",
                                compat=compat_mode))
    console.print(f"Settings: {settings_text(summary['settings'])}", highlight=False,
                  soft_wrap=True)
    if summary.get("scenes"):
        console.print(scene_table(summary))
    console.print(f"Output: {out} (summary: {out / 'summary.json'})", highlight=False,
                  soft_wrap=True)
