"""An attack run over a dataset: particles per pair, the optimisation, outputs, resumption.

Like :mod:`weathergen.render.job` for ``render``: :func:`run_attack` takes an :class:`AttackJob`
and reports through callbacks, so the command line only wires options and shows progress. The loop
itself is :func:`weathergen.attack.attack_pair`; the folder and its files belong to
:mod:`weathergen.outputs`.

Particles come from :func:`weathergen.render.pair_particles`, seeded per pair exactly as ``render``
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
from ..engine import render_pair
from ..errors import ConfigError, WeatherGenError
from ..io.images import to_uint8
from ..models import get_model
from ..outputs import (ATTACK_FOLDER, MANIFEST, AttackPairOutput, PairOutput, pair_metadata,
                       prepare_folder, read_attack_manifest, read_pair_summary,
                       write_attack_manifest, write_attack_pair)
from ..outputs.metadata import identity_arrays
from ..render.particles import pair_particles, pair_seed, weather_seed
from .lp import LpSettings, lp_attack_pair
from .pair import PairSummary, StepRecord, attack_pair, mean_summary, summarize_pair
from .settings import AttackSettings
from .targets import TargetSpec, read_target_flow


@dataclass
class AttackJob:
    """Everything an attack run needs."""

    dataset: Dataset
    out: Path
    model: str
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
    resume: bool = False
    overwrite: bool = False
    command: list = field(default_factory=list)
    #: set for an Lp baseline (``pcfa``, ``ifgsm``) instead of weather: frames are perturbed
    lp: Optional[LpSettings] = None

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
                "model": {"name": self.model, "checkpoint": str(self.checkpoint)
                          if self.checkpoint is not None else None, "iters": self.iters},
            }
        return {
            "preset_name": self.preset_name, "preset": self.preset.to_dict(), "seed": self.seed,
            "input": self.dataset.describe(),
            "outputs": {"pass": self.pass_name, "format": "png", "geometry": True},
            "particles_from": str(self.particles_from) if self.particles_from else None,
            "attack": {**self.settings.to_dict(), "target": self.target.describe(),
                       "configuration": self.config_name},
            "model": {"name": self.model, "checkpoint": str(self.checkpoint)
                      if self.checkpoint is not None else None, "iters": self.iters},
        }


@dataclass
class PairReport:
    """What happened to one pair: ``status`` is written, skipped (done earlier) or failed."""

    pair: str
    status: str
    summary: Optional[PairSummary] = None
    message: str = ""


def attack_one(job: AttackJob, model, pair, target_file_flow=None,
               on_step: Callable[[StepRecord], None] = lambda r: None) -> PairSummary:
    """Attack one loaded pair and write its outputs; return its figures."""
    if job.lp is not None:
        return lp_attack_one(job, model, pair, target_file_flow, on_step)
    start = time.perf_counter()
    particles = pair_particles(pair, job.preset, job.seed,
                               world_up=getattr(job.dataset, "world_up", "auto"),
                               particles_from=job.particles_from)
    result = attack_pair(model, pair, particles, job.settings, job.target, device=job.device,
                         target_file_flow=target_file_flow, on_step=on_step)
    # What is written is the best record at storage precision, rendered and rounded to the
    # 8-bit PNG frames; the adversarial flow is the network's flow on exactly those frames, so
    # the figures describe the files on disk (`evaluate --weather OUT` measures the same).
    best = result.best_particles.quantized()
    with torch.no_grad():
        rendered = render_pair(pair, best, beta=job.settings.beta, device=job.device)
    frames = tuple(to_uint8(img[0].permute(1, 2, 0).cpu().numpy())
                   for img in (rendered.image1, rendered.image2))
    stored = [torch.from_numpy(f).permute(2, 0, 1)[None].float().div(255).to(job.device)
              for f in frames]
    with torch.no_grad():
        adversarial = model(*stored).cpu()
    summary = summarize_pair(str(pair.id), result, adversarial, pair.flow, pair.flow_valid,
                             seconds=time.perf_counter() - start)
    opacity = tuple(a[0, 0].cpu().numpy() for a in (rendered.opacity1, rendered.opacity2))
    meta = pair_metadata(best, pair.id, weather_seed(job.preset, job.seed, pair.id), job.preset.to_dict(),
                         job.preset_name)
    flows = {"benign": result.benign_flow, "initial": result.initial_flow,
             "adversarial": adversarial, "target": result.target}
    out = AttackPairOutput.of(job.out, pair.id, job.pass_name)
    write_attack_pair(out, pair.to("cpu"), frames, opacity, meta, flows, result.history,
                      asdict(summary))
    return summary


def lp_pair_output(job: AttackJob, pair_id) -> AttackPairOutput:
    """Where an Lp-attacked pair goes: the attack layout, with float EXR frames besides the PNGs
    (an Lp perturbation is finer than the 8-bit steps of a PNG)."""
    return AttackPairOutput(PairOutput.of(job.out, pair_id, job.pass_name, "both", geometry=True))


def lp_attack_one(job: AttackJob, model, pair, target_file_flow=None,
                  on_step: Callable[[StepRecord], None] = lambda r: None) -> PairSummary:
    """Attack one loaded pair with an Lp baseline and write the same files as a weather attack.

    The figures describe the float frames of the best step (written as EXR; the PNG frames are
    those frames rounded to 8 bits). The metadata holds the pair's identity and the Lp settings,
    no particles.
    """
    start = time.perf_counter()
    seed = pair_seed(job.seed, pair.id)
    p = pair.to(job.device)
    result = lp_attack_pair(model, p.image1[None], p.image2[None], job.lp, job.target,
                            seed=seed, target_file_flow=target_file_flow, on_step=on_step)
    summary = summarize_pair(str(pair.id), result, result.best_flow, pair.flow, pair.flow_valid,
                             seconds=time.perf_counter() - start)
    frames = tuple(f[0].permute(1, 2, 0).numpy() for f in result.best_frames)
    opacity = tuple(torch.zeros(f.shape[:2]).numpy() for f in frames)
    meta = identity_arrays(pair.id, seed, {}, job.preset_name)
    meta["lp_attack"] = np.array(json.dumps(job.lp.to_dict()))
    flows = {"benign": result.benign_flow, "initial": result.initial_flow,
             "adversarial": result.best_flow, "target": result.target}
    write_attack_pair(lp_pair_output(job, pair.id), pair.to("cpu"), frames, opacity, meta, flows,
                      result.history, asdict(summary))
    return summary


def prepare_attack_folder(job: AttackJob) -> Optional[dict]:
    """Create or reuse the job's folder (see :func:`~weathergen.outputs.prepare_folder`); return
    the manifest of the run it resumes, if any."""
    out = Path(job.out)
    previous = None
    if not job.overwrite and (out / MANIFEST).exists() and any(out.iterdir()):
        previous = read_attack_manifest(out) if (out / ATTACK_FOLDER.marker).exists() else None
    prepare_folder(out, ATTACK_FOLDER, job.config(),
                   None if previous is None else previous.get("config", {}),
                   resume=job.resume, overwrite=job.overwrite)
    return previous


def run_attack(job: AttackJob,
               on_start: Callable[[int], None] = lambda n: None,
               on_pair_start: Callable[[int, str], None] = lambda i, name: None,
               on_step: Callable[[StepRecord], None] = lambda r: None,
               on_pair_done: Callable[[PairReport], None] = lambda r: None) -> dict:
    """Attack every selected pair; return the manifest's summary (mean figures).

    Pairs complete on disk are skipped when resuming. The manifest is rewritten after every pair,
    so an interrupted run (Ctrl-C) keeps what it finished.
    """
    config = job.config()
    # Everything that can fail on bad options fails before the output folder is touched.
    refs = job.dataset.pairs()
    if not refs:
        raise ConfigError("the selection holds no frame pairs")
    model = get_model(job.model, job.checkpoint, device=job.device, iters=job.iters,
                      download=job.download, gradient_checkpointing=job.gradient_checkpointing)
    target_file_flow = read_target_flow(job.target.path) if job.target.kind == "file" else None
    previous = prepare_attack_folder(job)

    pairs_entry: dict = dict(previous.get("pairs", {})) if previous else {}
    runs = list(previous.get("runs", [])) if previous else []
    run = {"command": job.command, "device": job.device,
           "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "written": 0, "skipped": 0, "failed": 0}
    runs.append(run)
    summaries: list[PairSummary] = []

    def save():
        write_attack_manifest(job.out, config, pairs_entry, mean_summary(summaries), runs)

    on_start(len(refs))
    t0 = time.perf_counter()
    try:
        for i, ref in enumerate(refs):
            out = (lp_pair_output(job, ref.id) if job.lp is not None
                   else AttackPairOutput.of(job.out, ref.id, job.pass_name))
            on_pair_start(i, str(ref.id))
            if not job.overwrite and out.is_complete():
                stored = read_pair_summary(out)
                if stored is not None:
                    summary = PairSummary.from_dict(stored)
                    summaries.append(summary)
                    pairs_entry[ref.id.key] = {"status": "written", **stored}
                    run["skipped"] += 1
                    on_pair_done(PairReport(str(ref.id), "skipped", summary))
                    continue
            try:
                pair = job.dataset.load(ref)
                summary = attack_one(job, model, pair, target_file_flow, on_step)
            except WeatherGenError as exc:
                pairs_entry[ref.id.key] = {"status": "failed", "pair": str(ref.id),
                                           "message": str(exc)}
                run["failed"] += 1
                on_pair_done(PairReport(str(ref.id), "failed", message=str(exc)))
                save()
                continue
            summaries.append(summary)
            pairs_entry[ref.id.key] = {"status": "written", **asdict(summary)}
            run["written"] += 1
            on_pair_done(PairReport(str(ref.id), "written", summary))
            save()
    finally:
        run["seconds"] = round(time.perf_counter() - t0, 3)
        save()
    return mean_summary(summaries)
