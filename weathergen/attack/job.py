"""An attack run over a dataset: particles per pair, the optimisation, outputs, resumption.

Like :mod:`weathergen.render.job` for ``render``: :func:`run_attack` takes an :class:`AttackJob`
and reports through callbacks, so the command line only wires options and shows progress. The loop
itself is :func:`weathergen.attack.attack_pair`; the folder and its files belong to
:mod:`weathergen.outputs`.

Particles come from :func:`weathergen.jobs.pair_particles`, seeded per pair exactly as ``render``
seeds them, so ``attack --seed S`` starts from the weather that ``render --seed S`` writes for the
same preset.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from ..datasets import Dataset
from ..engine import CombinedPreset
from ..engine.rendering.budget import check_pair_memory
from ..errors import ConfigError, OutputError, WeatherGenError
from ..flow import weather_mask
from ..execution import check_executor, ray_gpus_for, ray_map, where_ran, worker_device
from ..io.atomic import write_error
from ..memory import failure_message
from ..words import counted
from ..models import AUTOCAST, Network, get_model, probe_network, resolve_network, resolve_precision
from ..outputs import (ATTACK_FOLDER, MANIFEST, AttackPairOutput, PairOutput, claim_folder, lock_file,
                       pair_metadata, read_pair_summary, write_attack_manifest, write_attack_pair)
from ..outputs.metadata import identity_arrays
from ..jobs import (depth_note, frame2_note, layer_seeds, pair_particles, pair_seed,
                    scene_airlight, scene_firsts, scene_key, selected_pairs,
                    torch_threads, visibility_of, weather_scaling, weather_seed)
from .lp import LpSettings, lp_attack_batch
from .figures import PairSummary, mean_summary, summarize_pair, written_flow
from .pair import StepRecord, attack_batch
from .record import run_settings
from .sequence import (check_sequence_preset, check_sequence_settings, compare_alone,
                       scene_figures, scene_units, sequence_results)
from .settings import AttackSettings
from .targets import TargetSpec, read_target_flow


@dataclass
class AttackJob:
    """Everything an attack run needs."""

    dataset: Dataset
    out: Path
    model: Network                      # a name is resolved when the job is made
    checkpoint: Optional[str]
    preset: object                       # weathergen.engine.Preset (None for an Lp attack)
    preset_name: str
    settings: Optional[AttackSettings]   # None for an Lp attack
    target: TargetSpec = TargetSpec("zero")
    iters: Optional[int] = None
    seed: int = 0
    device: str = "cpu"
    particles_from: Optional[Path] = None
    config_name: Optional[str] = None
    pass_name: str = ""
    gradient_checkpointing: bool = False
    download: bool = False
    #: mixed precision as asked (``--amp``/``--no-amp``); None: the network's paper setting
    #: on CUDA, off elsewhere (see :meth:`amp_setting`)
    amp: Optional[bool] = None
    #: the network's precision as asked (``--precision``, exclusive with ``amp``); None: ``amp``'s
    precision: Optional[str] = None
    resume: bool = False
    overwrite: bool = False
    command: list = field(default_factory=list)
    #: set for an Lp baseline (``pcfa``, ``ifgsm``) instead of weather: frames are perturbed
    lp: Optional[LpSettings] = None
    batch_size: int = 1                 # pairs of one size optimised together
    executor: str = "local"             # "local" or "ray" (weathergen.execution)
    ray_address: Optional[str] = "auto"
    threads: Optional[int] = None       # torch threads of each unit (None: leave as is)
    scene_firsts: dict = field(default_factory=dict)   # each scene's first selected pair
    sequence: bool = False              # one weather per scene (weathergen.attack.sequence)
    stereo: bool = False                # sequence: against the dataset's second camera too

    def __post_init__(self):
        self.model = resolve_network(self.model)

    def precision_setting(self) -> str:
        """The precision the network runs in (:func:`~weathergen.models.resolve_precision` of the
        job's network, requests and device).

        Raises:
            ConfigError: a request the device or the network cannot meet (``--amp`` off CUDA or
                for a network without a mixed-precision mode, a refused ``--precision``).
        """
        return resolve_precision(self.model, self.precision, self.amp, self.device)

    def amp_setting(self) -> bool:
        """Whether the network runs under autocast (:meth:`precision_setting` bf16 or fp16)."""
        return self.precision_setting() in AUTOCAST

    def model_config(self) -> dict:
        """The network as recorded in the manifest: name, checkpoint, iterations, precision; for
        a network from outside the package the code's ``source`` (file and sha256, see
        :meth:`~weathergen.models.Network.source`)."""
        record = self.model.source()
        config = {"name": self.model.name, "checkpoint": str(self.checkpoint)
                  if self.checkpoint is not None else None, "iters": self.iters,
                  "amp": self.amp_setting()}
        if self.precision is not None:      # asked for: recorded (a run without it resumes as before)
            config["precision"] = self.precision_setting()
        return config if record is None else {**config, "source": record}

    def config(self) -> dict:
        """What must agree between an interrupted run and its resumption."""
        if self.lp is not None:
            return {
                "preset_name": self.preset_name, "preset": None, "seed": self.seed,
                "input": self.dataset.describe(),
                "outputs": {"pass": self.pass_name, "format": "both", "geometry": True},
                "particles_from": None,
                "attack": {"method": self.lp.method, **self.lp.to_dict(),
                           "target": self.target.describe(), "configuration": None},
                "model": self.model_config(),
            }
        return {
            "preset_name": self.preset_name, "preset": self.preset.to_dict(), "seed": self.seed,
            "input": self.dataset.describe(),
            "outputs": {"pass": self.pass_name, "format": "png", "geometry": True},
            "particles_from": str(self.particles_from) if self.particles_from else None,
            "attack": {**self.settings.to_dict(), "target": self.target.describe(),
                       "configuration": self.config_name,
                       **({"sequence": True} if self.sequence else {}),
                       **({"stereo": True} if self.stereo else {})},
            "model": self.model_config(),
        }


@dataclass
class PairReport:
    """What happened to one pair: ``status`` is written, skipped (done earlier) or failed.
    ``ran``: where and on what it was computed (:func:`~weathergen.execution.where_ran`, plus
    the size of its batch)."""

    pair: str
    status: str
    summary: Optional[PairSummary] = None
    message: str = ""
    key: str = ""
    ran: Optional[dict] = None
    #: what the reader found odd about the input (``"FILE: what"`` lines, e.g. a grey frame beside
    #: a colour one): the pair is attacked all the same
    warnings: list = field(default_factory=list)
    #: particle centres frame 1 and frame 2 show before the optimisation (None for an Lp attack)
    visible: Optional[tuple] = None
    #: a paper preset's pair whose frame 2 shows fewer than half of them (strong camera motion;
    #: see :func:`weathergen.jobs.few_in_frame2`)
    few_in_frame2: bool = False
    #: each frame's shares of measured, completed, sky and unknown depth, where the reader says
    depth_provenance: list = field(default_factory=list)


_LOADED: dict = {}


def job_model(job: AttackJob, device: Optional[str] = None):
    """The job's network on ``device`` (default the job's), loaded once per process."""
    device = device or job.device
    precision = resolve_precision(job.model, job.precision, job.amp, device)
    key = (job.model, str(job.checkpoint), job.iters, device, job.gradient_checkpointing, precision)
    if key not in _LOADED:
        _LOADED.clear()                     # one network per process at a time
        _LOADED[key] = get_model(job.model, job.checkpoint, device=device, iters=job.iters,
                                 download=job.download,
                                 gradient_checkpointing=job.gradient_checkpointing,
                                 precision=precision)
        _LOADED[key].padding = getattr(job.dataset, "padding", "even")  # the benchmark's protocol
    return _LOADED[key]


def probe_job_network(job: AttackJob, model, ref) -> None:
    """Run the job's network once on the pair ``ref`` (the first), forward and backward: a flow
    that is not finite, of another shape or without a gradient to the frames is refused in one
    line (:func:`~weathergen.models.probe_network`) before anything is written. A first pair
    that does not load (it fails alone later) gives way to a small random pair."""
    try:
        pair = job.dataset.load(ref)
    except WeatherGenError:
        return probe_network(model, job.model.label, gradient=True)
    probe_network(model, job.model.label, pair.image1[None].to(job.device),
                  pair.image2[None].to(job.device), gradient=True)


def attack_refs(job: AttackJob, refs: list, model=None, target_file_flow=None,
                on_step: Callable[[str, StepRecord], None] = lambda name, r: None,
                device: Optional[str] = None) -> list[PairReport]:
    """Load, attack and write some pairs; one report per pair, in the order of ``refs``.

    Pairs of one size are optimised together (:func:`~weathergen.attack.attack_batch`, or
    :func:`~weathergen.attack.lp_attack_batch` for an Lp baseline), pairs of other sizes in
    batches of their own. A pair whose input is bad fails alone; an error in the optimisation
    fails the pairs of its batch. This is the work unit of every executor.
    """
    with torch_threads(job.threads):
        return _attack_refs(job, refs, model, target_file_flow, on_step, device or job.device)


def _attack_refs(job: AttackJob, refs: list, model, target_file_flow, on_step,
                 device: str) -> list[PairReport]:
    if model is None:
        model = job_model(job, device)
    if target_file_flow is None and job.target.kind == "file":
        target_file_flow = read_target_flow(job.target.path)
    reports: dict[str, PairReport] = {}
    groups, shown = _loaded_groups(job, refs, device, reports)
    for group in groups.values():
        _attack_group(job, model, group, device, target_file_flow, on_step, reports, shown)
    return [reports[ref.id.key] for ref in refs]


def _loaded_groups(job: AttackJob, refs: list, device: str, reports: dict
                   ) -> tuple[dict, dict]:
    """``(groups, shown)``: the pairs of ``refs`` by size, each as ``(ref, pair, particles,
    seconds to load)``, and by pair key what its record shows before optimising (the particle
    centres each frame shows, whether frame 2 shows few); a pair that fails to load gets its
    report in ``reports``."""
    groups: dict[tuple, list] = {}
    shown: dict[str, tuple] = {}
    for ref in refs:
        start = time.perf_counter()
        try:
            pair, particles = _loaded(job, ref, device, len(refs))
        except (WeatherGenError, MemoryError, RuntimeError) as exc:
            reports[ref.id.key] = PairReport(str(ref.id), "failed", key=ref.id.key,
                                             message=failure_message(exc, "--batch-size"))
            continue
        groups.setdefault(pair.size, []).append((ref, pair, particles,
                                                 time.perf_counter() - start))
        if particles is not None:
            shown[ref.id.key] = visibility_of(pair, particles)
    return groups, shown


def _loaded(job: AttackJob, ref, device: str, share: int) -> tuple:
    """Pair ``ref`` and its starting record (None for an Lp baseline), the pair's memory checked
    for ``share`` pairs on ``device``."""
    pair = job.dataset.load(ref)
    if job.lp is None:      # the weather's part; the network's is not estimated
        check_pair_memory(pair, job.preset, device, share=share)
    airlight = None if job.lp is not None or job.particles_from is not None else \
        scene_airlight(job.dataset, ref.id, job.scene_firsts, job.preset)
    particles = None if job.lp is not None else pair_particles(
        pair, job.preset, job.seed, world_up=getattr(job.dataset, "world_up", "auto"),
        frame_rate=job.dataset.frame_rate, particles_from=job.particles_from,
        airlight=airlight)
    return pair, particles


def _attack_group(job: AttackJob, model, group: list, device: str, target_file_flow, on_step,
                  reports: dict, shown: dict) -> None:
    """Optimise a group of pairs of one size (items of :func:`_loaded_groups`) and write them,
    each pair's report in ``reports``; an error in the optimisation fails the whole group."""
    start = time.perf_counter()
    names = [str(ref.id) for ref, _, _, _ in group]
    pairs = [g[1] for g in group]
    step = lambda i, record: on_step(names[i], record)     # noqa: E731
    try:
        results, alone = _optimise(job, model, pairs, [g[2] for g in group], device,
                                   target_file_flow, step)
    except (WeatherGenError, MemoryError, RuntimeError) as exc:
        message = failure_message(exc, "--batch-size")
        for ref, _, _, _ in group:
            reports[ref.id.key] = PairReport(str(ref.id), "failed", message=message,
                                             key=ref.id.key)
        return
    share = (time.perf_counter() - start) / len(group)
    ran = {**where_ran(device), "batch": len(group)}
    write = write_lp_pair if job.lp is not None else write_attacked_pair
    for i, ((ref, pair, _, spent), result) in enumerate(zip(group, results)):
        begin = time.perf_counter()
        try:
            summary = write(job, model, pair, result, device)
            if alone is not None:
                compare_alone(job, model, pair, result, alone[i], summary, device)
        except OSError as exc:      # a full or unwritable disk stops the run, as render's
            raise write_error(exc, job.out, "then rerun with ${resume}") from None
        summary.seconds = spent + share + time.perf_counter() - begin
        visible, few = shown.get(ref.id.key, (None, False))
        reports[ref.id.key] = PairReport(str(ref.id), "written", summary, key=ref.id.key,
                                         ran=ran, warnings=list(pair.meta.get("warnings", [])),
                                         visible=visible, few_in_frame2=few,
                                         depth_provenance=pair.meta.get("depth_provenance", []))


def _optimise(job: AttackJob, model, pairs: list, particles: list, device, target_file_flow,
              on_step) -> tuple[list, Optional[list]]:
    """A group's optimisation: its results, and a sequence attack's pairs attacked alone."""
    if job.lp is not None:
        return lp_attack_batch(
            model, torch.stack([p.image1 for p in pairs]).to(device),
            torch.stack([p.image2 for p in pairs]).to(device), job.lp, job.target,
            seeds=[pair_seed(job.seed, p.id) for p in pairs],
            target_file_flow=target_file_flow, on_step=on_step), None
    if job.sequence:
        return sequence_results(job, model, pairs, particles, device, target_file_flow, on_step)
    return attack_batch(model, pairs, particles, job.settings, job.target, device=device,
                        target_file_flow=target_file_flow, on_step=on_step), None


def write_attacked_pair(job: AttackJob, model, pair, result, device) -> PairSummary:
    """Write one optimised pair's outputs; return its figures."""
    # What is written is the best record at storage precision, rendered and rounded to the
    # 8-bit PNG frames; the adversarial flow is the network's flow on exactly those frames, so
    # the figures describe the files on disk (`evaluate --weather OUT` measures the same).
    best, rendered, frames, adversarial = written_flow(model, pair, result.best_particles,
                                                       job.settings.beta, device)
    covered = weather_mask(rendered.opacity1, rendered.opacity2)[0, 0].cpu()
    summary = summarize_pair(str(pair.id), result, adversarial, pair.flow, pair.flow_valid,
                             compat=job.settings.compat, covered=covered)
    summary.particles = best.count
    opacity = tuple(a[0, 0].cpu().numpy() for a in (rendered.opacity1, rendered.opacity2))
    seeds = (layer_seeds(job.preset, job.seed, pair.id)
             if isinstance(job.preset, CombinedPreset) else None)
    meta = pair_metadata(best, pair.id, weather_seed(job.preset, job.seed, pair.id),
                         job.preset.to_dict(), job.preset_name, seeds,
                         scaling=weather_scaling(job.preset, pair, job.particles_from))
    flows = {"benign": result.benign_flow, "initial": result.initial_flow,
             "adversarial": adversarial, "target": result.target}
    out = pair_output(job, pair.id)
    write_attack_pair(out, pair.to("cpu"), frames, opacity, meta, flows, result.history,
                      asdict(summary))
    return summary


def lp_pair_output(job: AttackJob, pair_id) -> AttackPairOutput:
    """Where an Lp-attacked pair goes: the attack layout, with float EXR frames besides the PNGs
    (an Lp perturbation is finer than the 8-bit steps of a PNG)."""
    return AttackPairOutput(PairOutput.of(job.out, pair_id, job.pass_name, "both", geometry=True,
                                          native=job.dataset.native_flow))


def pair_output(job: AttackJob, pair_id) -> AttackPairOutput:
    """Where the job writes a pair."""
    return (lp_pair_output(job, pair_id) if job.lp is not None
            else AttackPairOutput.of(job.out, pair_id, job.pass_name,
                                     native=job.dataset.native_flow))


def write_lp_pair(job: AttackJob, model, pair, result, device) -> PairSummary:
    """Write one Lp-attacked pair with the same files as a weather attack; return its figures.

    The figures describe the float frames of the best step (written as EXR; the PNG frames are
    those frames rounded to 8 bits). The metadata holds the pair's identity and the Lp settings,
    no particles.
    """
    summary = summarize_pair(str(pair.id), result, result.best_flow, pair.flow, pair.flow_valid)
    frames = tuple(f[0].permute(1, 2, 0).numpy() for f in result.best_frames)
    opacity = tuple(np.zeros(f.shape[:2], dtype=np.float32) for f in frames)
    meta = identity_arrays(pair.id, pair_seed(job.seed, pair.id), {}, job.preset_name)
    meta["lp_attack"] = np.array(json.dumps(job.lp.to_dict()))
    flows = {"benign": result.benign_flow, "initial": result.initial_flow,
             "adversarial": result.best_flow, "target": result.target}
    write_attack_pair(lp_pair_output(job, pair.id), pair.to("cpu"), frames, opacity, meta, flows,
                      result.history, asdict(summary))
    return summary


def run_summary(job: AttackJob, rows: list[PairSummary]) -> dict:
    """The run's summary (``summary.json``): the means over pairs (:func:`mean_summary`), the
    attack's ``compat`` mode (None for an Lp attack) and the precision the network ran in
    (``amp``: under autocast; ``precision``: float32, tf32, bf16 or fp16); a sequence attack's
    ``scenes`` (:func:`~weathergen.attack.sequence.scene_figures`)."""
    summary = {**mean_summary(rows), "compat": job.settings.compat if job.lp is None else None,
               "amp": job.amp_setting(), "precision": job.precision_setting(),
               "settings": job_settings(job)}
    if job.sequence:
        summary["scenes"] = scene_figures(rows)
    return summary


def job_settings(job: AttackJob) -> dict:
    """The run's settings record (:func:`~weathergen.attack.record.run_settings`): the network as
    the job runs it, the steps and the learning rates of its optimiser (a weather attack's by
    group, :attr:`~weathergen.attack.AttackSettings.learning_rates`; an Lp attack's ``lr``), its
    seed."""
    if job.lp is not None:
        steps, rates = job.lp.steps, {"lr": job.lp.lr}
    else:
        steps, rates = job.settings.steps, job.settings.learning_rates
    return run_settings(job.model, job.checkpoint, iters=job.iters, precision=job.precision_setting(),
                        padding=getattr(job.dataset, "padding", "even"), steps=steps,
                        learning_rates=rates, seed=job.seed)


def _last_save(save, run: dict, stopped_by) -> None:
    """Write the manifest at the end of a run; when the disk refuses, say so without hiding why
    the run stopped (as render does): a write that failed first keeps its message, with the
    manifest's added; an interruption or a bug goes through as it is."""
    try:
        save()
    except OutputError as exc:
        if stopped_by is None:
            raise
        if isinstance(stopped_by, OutputError) and str(stopped_by) != str(exc):
            raise OutputError(f"{stopped_by.args[0]}; the manifest could not be updated either; "
                              f"${{resume}} finds the {counted(run['written'], 'pair')} "
                              f"finished in this run on disk") from None


def _complete(job: AttackJob, ref, refs: list) -> bool:
    """Whether a pair is finished on disk; a sequence attack's, whether its whole scene is (a
    scene with an unfinished pair is redone whole)."""
    scene = [r for r in refs if scene_key(r.id) == scene_key(ref.id)] if job.sequence else [ref]
    return all(pair_output(job, r.id).is_complete() for r in scene)


def _ray_attack_unit(job: AttackJob, refs: list) -> list[PairReport]:
    """A Ray task: attack some pairs on the device this task was given."""
    return attack_refs(job, refs, device=worker_device(job.device, "ray"))


#: The lock file of an attack folder: one run at a time writes it.
ATTACK_LOCK = lock_file()


def run_attack(job: AttackJob,
               on_start: Callable[[int], None] = lambda n: None,
               on_step: Callable[[str, StepRecord], None] = lambda name, r: None,
               on_pair_done: Callable[[PairReport], None] = lambda r: None,
               on_note: Callable[[str], None] = lambda text: None) -> dict:
    """Attack every selected pair; return the manifest's summary (mean figures).

    Pairs complete on disk are skipped when resuming. Pairs go in work units of
    ``job.batch_size`` (each optimised together where they share a size), run here or as Ray
    tasks (``job.executor``). The manifest is rewritten after every unit, so an interrupted run
    (Ctrl-C, or a killed driver) keeps what it finished. ``on_step`` receives the pair's name and
    each step (local executor only: Ray tasks report whole pairs); ``on_note`` warnings worth a
    line (a stale lock taken over, a gap in a scene's frame numbering, the pairs marked
    ``few_in_frame2``, once per run). The output folder is claimed for the run
    (:func:`~weathergen.outputs.claim_folder`): a second run in it raises
    :class:`~weathergen.errors.FolderBusy`.
    """
    check_executor(job.executor)
    if job.batch_size < 1:
        raise ConfigError(f"${{batch_size}} must be >= 1 (got {job.batch_size})")
    job.precision_setting()                # a request the device or network cannot meet
    if job.stereo and not job.sequence:
        raise ConfigError("${stereo} applies to ${sequence}: one weather seen by both cameras")
    if job.sequence:
        check_sequence_preset(job.preset, job.preset_name)
        check_sequence_settings(job.settings)
        if job.particles_from is not None:
            raise ConfigError("${particles_from}: a sequence attack starts from the weather "
                              "field of ${seed}, not from stored particles")
    # Everything that can fail on bad options fails before the output folder is touched.
    refs = selected_pairs(job.dataset, job.particles_from, on_note)
    if not refs:
        raise ConfigError(job.dataset.no_pairs_message())
    job.scene_firsts = scene_firsts(refs)
    local = job.executor == "local"
    # The driver of a Ray run checks the network and its checkpoint on the CPU.
    model = job_model(job) if local else get_model(
        job.model, job.checkpoint, device="cpu", iters=job.iters, download=job.download)
    if local:
        probe_job_network(job, model, refs[0])
    else:                                   # the driver: a small pair on the CPU
        probe_network(model, job.model.label, gradient=True)
    target_file_flow = read_target_flow(job.target.path) if job.target.kind == "file" else None
    if not local:
        model = None
    with claim_folder(job.out, ATTACK_FOLDER, job.config(), resume=job.resume,
                      overwrite=job.overwrite, on_note=on_note) as claim:
        return _attack_locked(job, refs, model, target_file_flow, claim.previous, on_start,
                              on_step, on_pair_done, on_note)


def _attack_locked(job, refs, model, target_file_flow, previous, on_start, on_step,
                   on_pair_done, on_note) -> dict:
    book = _Manifest(job, refs, previous, on_pair_done)
    on_start(len(refs))
    t0 = time.perf_counter()
    stopped_by = None
    try:
        todo = [ref for ref in refs if not _skipped(job, ref, refs, book)]
        # the work units: batch_size pairs each, or a sequence attack's scenes
        units = (scene_units(todo) if job.sequence
                 else [todo[i:i + job.batch_size] for i in range(0, len(todo), job.batch_size)])
        for reports in _unit_reports(job, units, model, target_file_flow, on_step):
            for report in reports:
                book.record(report)
            book.save()
    except BaseException as exc:
        stopped_by = exc
        raise
    finally:
        book.run["seconds"] = round(time.perf_counter() - t0, 3)
        _last_save(book.save, book.run, stopped_by)
    written = book.written
    for note in filter(None, (depth_note([(r.pair, {"depth_provenance": r.depth_provenance})
                                          for r in written]),
                              frame2_note([(r.pair, r.visible) for r in written if r.few_in_frame2],
                                          job.preset_name))):
        on_note(note)
    return book.summary()


def _skipped(job: AttackJob, ref, refs: list, book: "_Manifest") -> bool:
    """Whether pair ``ref`` is complete on disk from an earlier run (then recorded as skipped)."""
    if job.overwrite or not _complete(job, ref, refs):
        return False
    stored = read_pair_summary(pair_output(job, ref.id))
    if stored is None:
        return False
    book.record(PairReport(str(ref.id), "skipped", PairSummary.from_dict(stored), key=ref.id.key))
    return True


def _unit_reports(job: AttackJob, units: list, model, target_file_flow, on_step):
    """The reports of each work unit, as each is done: here (lazily) or on Ray's workers."""
    if job.executor == "local":
        return (attack_refs(job, unit, model, target_file_flow, on_step) for unit in units)
    return ray_map(_ray_attack_unit, [(job, unit) for unit in units],
                   address=job.ray_address, num_gpus=ray_gpus_for(job.device))


class _Manifest:
    """A run's manifest as it goes: the earlier runs' pair entries and runs, this run's counts,
    the summaries of the pairs written or skipped and the reports of those written."""

    def __init__(self, job: AttackJob, refs: list, previous: Optional[dict], on_pair_done):
        self.job, self.on_pair_done, self.config = job, on_pair_done, job.config()
        self.order = [ref.id.key for ref in refs]
        self.pairs: dict = dict(previous.get("pairs", {})) if previous else {}
        self.runs = list(previous.get("runs", [])) if previous else []
        self.run = {"command": job.command, "device": job.device, "executor": job.executor,
                    "batch_size": job.batch_size,
                    "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "written": 0, "skipped": 0, "failed": 0}
        notes = job.dataset.scene_notes()          # e.g. a gap in a scene's frame numbering
        if notes:
            self.run["notes"] = notes
        self.runs.append(self.run)
        self.summaries: dict[str, PairSummary] = {}
        self.written: list[PairReport] = []

    def summary(self) -> dict:
        return run_summary(self.job, [self.summaries[k] for k in self.order
                                      if k in self.summaries])

    def save(self) -> None:
        ordered = {k: self.pairs[k] for k in self.order if k in self.pairs}
        ordered.update({k: v for k, v in self.pairs.items() if k not in ordered})
        try:
            write_attack_manifest(self.job.out, self.config, ordered, self.summary(), self.runs)
        except OSError as exc:
            raise write_error(exc, self.job.out / MANIFEST, "then rerun with ${resume}") from None

    def record(self, report: PairReport) -> None:
        if report.status == "failed":
            self.pairs[report.key] = {"status": "failed", "pair": report.pair,
                                      "message": report.message}
        else:
            self.summaries[report.key] = report.summary
            self.pairs[report.key] = _written_entry(report, self.pairs.get(report.key, {}))
        self.run[report.status] += 1
        if report.status == "written":
            self.written.append(report)
        self.on_pair_done(report)


def _written_entry(report: PairReport, old: dict) -> dict:
    """The manifest's entry of a pair written or skipped, what the report lacks from ``old``."""
    ran = report.ran if report.ran is not None else old.get("ran")
    warnings = report.warnings if report.status == "written" else old.get("warnings", [])
    sampled = ({"visible": list(report.visible), "few_in_frame2": report.few_in_frame2}
               if report.visible is not None else
               {k: old[k] for k in ("visible", "few_in_frame2") if k in old})
    return {"status": "written", **asdict(report.summary), **({"ran": ran} if ran else {}),
            **({"warnings": warnings} if warnings else {}), **sampled,
            **({"depth_provenance": report.depth_provenance} if report.depth_provenance else {})}
