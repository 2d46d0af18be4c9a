"""The render job over a dataset: selection, per-pair particles, workers, resumption, the manifest.

The job is independent of the command line: :func:`run_render` takes a :class:`RenderJob` and calls
back with :class:`PairResult` objects, so the CLI only wires options and reports progress.

Determinism: each pair's seed is derived from the run seed and the pair's identity (never from its
position in the run), and each pair is rendered by itself with a fixed number of threads, so the
bytes written do not depend on worker count, order, sharding or resumption.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from ..datasets import Dataset, PairRef, right_camera
from ..engine import (CombinedPreset, FieldPreset, LayeredParticles, View, load_templates,
                      particle_truth, reference_transforms, render_pair)
from ..engine.rendering.budget import check_pair_memory
from ..engine.rendering.renderer import pair_starts, render_first_frame
from ..engine.rendering.stereo import render_right, render_right_layers, stereo_view, warp_view_depth
from ..errors import ConfigError, NothingRendered, WeatherGenError
from ..execution import check_executor, ray_gpus_for, ray_map, where_ran, worker_device
from ..framepair import FramePairBatch, PairId
from ..jobs import (depth_note, frame2_note, layer_seeds, pair_particles,
                    scene_airlight, scene_firsts, selected_pairs, visibility_of, weather_scaling, weather_seed)
from ..outputs import RENDER_FOLDER, RightView, claim_folder, pair_metadata, write_pair_outputs
from ..io.atomic import write_error
from ..memory import available_memory, failure_message
from ..outputs.manifest import MANIFEST, jsonable
from ..workers import StopRequests, how_it_ended, init_worker, spawning
from ..words import counted
from .bookkeeping import forget_lost, pair_output, record_manifest, temporary_places
from .plan import auto_workers
from .shards import shard_refs

#: Every pair renders with this many intra-op threads, whatever the worker count: thread count can
#: change the order of floating-point reductions, and with it the output bytes.
RENDER_THREADS = 1


@dataclass
class RenderJob:
    """Everything a render run needs; picklable, so workers receive it whole."""

    dataset: Dataset
    out: Path
    preset: object                      # weathergen.engine.Preset
    preset_name: str
    seed: int = 0
    pass_name: str = ""
    fmt: str = "png"
    geometry: bool = True
    truth: bool = False                 # write the particle ground truth (flows, opacity)
    sequence: bool = False              # whole scenes, each frame once (field presets)
    stereo: bool = False                # also render the dataset's second (right) camera
    scene_ends: frozenset = frozenset() # sequence: pairs whose second frame no other pair writes
    scene_firsts: dict = field(default_factory=dict)  # each scene's first selected pair
    device: str = "cpu"
    particles_from: Optional[Path] = None
    appearance: dict = field(default_factory=dict)   # re-render overrides of Particles settings
    shard: tuple[int, int] = (1, 1)
    workers: int = 1                    # worker processes; 0: auto_workers() decides
    batch_size: int = 1                 # pairs rendered together (per worker)
    resume: bool = False
    overwrite: bool = False
    command: list = field(default_factory=list)
    executor: str = "local"             # "local" or "ray" (weathergen.execution)
    ray_address: Optional[str] = "auto"
    compat: str = "paper"               # reference: blur samples blended as the research code does

    def config(self) -> dict:
        """What must agree between the runs and shards that write one output folder."""
        return {
            "preset_name": self.preset_name,
            "preset": self.preset.to_dict(),
            "seed": self.seed,
            "input": self.dataset.describe(),
            "outputs": {"pass": self.pass_name, "format": self.fmt, "geometry": self.geometry,
                        **({"particle_truth": True} if self.truth else {}),
                        **({"sequence": True} if self.sequence else {}),
                        **({"stereo": True} if self.stereo else {})},
            "particles_from": str(self.particles_from.absolute()) if self.particles_from else None,
            "appearance": self.appearance,
            **({"compat": self.compat} if self.compat != "paper" else {}),
        }


@dataclass
class PairResult:
    """What happened to one pair."""

    key: str
    pair: str
    status: str                 # "written", "skipped" or "failed"
    seed: int
    seconds: float = 0.0
    bytes: int = 0
    message: str = ""
    visible: tuple = ()         # particle centres in view (in front of the scene) in frames 1, 2
    few_in_frame2: bool = False # a paper preset's pair that keeps < jobs.FRAME2_KEPT_MIN of them
    particles: Optional[int] = None   # written: particles in the pair's record (the count its
                                      # frame size gave, see the metadata's frame_scaling)
    input: dict = field(default_factory=dict)   # facts the reader reports (e.g. KITTI's pose fit)
    warnings: list = field(default_factory=list)  # what the reader found odd ("FILE: what" lines)
    ran: Optional[dict] = None  # where it was computed (weathergen.execution.where_ran) and batch


# -- one pair ------------------------------------------------------------------------------------
def render_batch(job: RenderJob, refs: list[PairRef]) -> list[PairResult]:
    """Load, sample (or reload), render and write some pairs. Never raises for bad input.

    Pairs of the same size are rendered together, as one batch (worth it on a GPU); each pair's
    particles come from its own seed, and no pixel of one pair depends on another pair, so the
    bytes written are those of rendering each pair alone.
    """
    torch.set_num_threads(RENDER_THREADS)
    results: dict[PairId, PairResult] = {}
    ready = []                                   # (ref, seed, pair, particles, seconds so far)
    for ref in refs:
        seed = weather_seed(job.preset, job.seed, ref.id)
        start = time.perf_counter()
        try:
            pair = job.dataset.load(ref)
            # Pairs drawn at the same time on one machine: a batch in each worker.
            share = max(1, job.workers if job.executor == "local" else 1) * max(1, job.batch_size)
            check_pair_memory(pair, job.preset, job.device, share=share)
            airlight = None if job.particles_from is not None else \
                scene_airlight(job.dataset, ref.id, job.scene_firsts, job.preset)
            particles = pair_particles(pair, job.preset, job.seed,
                                       world_up=getattr(job.dataset, "world_up", "auto"),
                                       frame_rate=job.dataset.frame_rate,
                                       particles_from=job.particles_from, appearance=job.appearance,
                                       preset_name=job.preset_name, sequence=job.sequence,
                                       airlight=airlight).for_compat(job.compat)
            ready.append((ref, seed, pair, particles, time.perf_counter() - start))
        except (WeatherGenError, MemoryError, RuntimeError) as exc:
            results[ref.id] = PairResult(ref.id.key, str(ref.id), "failed", seed,
                                         time.perf_counter() - start, message=_failure(exc))
    if job.sequence:
        for ref, seed, pair, particles, spent in ready:
            results[ref.id] = _sequence_pair(job, ref, seed, pair, particles, spent)
        return [results[ref.id] for ref in refs]
    groups: dict[tuple, list] = {}
    for item in ready:
        groups.setdefault(item[2].size, []).append(item)
    for group in groups.values():
        start = time.perf_counter()
        try:
            with torch.no_grad():
                if len(group) == 1:
                    rendered = render_pair(group[0][2], group[0][3], device=job.device)
                else:
                    rendered = render_pair(FramePairBatch.stack([g[2] for g in group]),
                                           [g[3] for g in group], device=job.device)
        except (WeatherGenError, MemoryError, RuntimeError) as exc:
            for ref, seed, _, _, spent in group:
                results[ref.id] = PairResult(ref.id.key, str(ref.id), "failed", seed, spent,
                                             message=_failure(exc))
            continue
        share = (time.perf_counter() - start) / len(group)
        ran = {**where_ran(job.device), "batch": len(group)}
        for i, (ref, seed, pair, particles, spent) in enumerate(group):
            start = time.perf_counter()
            results[ref.id] = _write_one(job, ref, seed, pair, particles, rendered, i)
            results[ref.id].seconds = spent + share + time.perf_counter() - start
            results[ref.id].ran = ran
    return [results[ref.id] for ref in refs]


def _failure(exc: Exception) -> str:
    """A failed pair's message (:func:`~weathergen.memory.failure_message`)."""
    return failure_message(exc, "--workers, --batch-size")


def _sequence_pair(job: RenderJob, ref: PairRef, seed: int, pair, particles, spent: float) -> PairResult:
    """One pair of a sequence render: its first frame (and its second where no later pair of the
    selection starts there), geometry, ground truth and particle record."""
    start = time.perf_counter()
    second = ref.id in job.scene_ends
    try:
        with torch.no_grad():
            if second:
                rendered = render_pair(pair, particles, device=job.device)
            else:
                image, alpha = render_first_frame(pair, particles, device=job.device)
                rendered = _FirstFrame(image1=image, opacity1=alpha)
    except (WeatherGenError, MemoryError, RuntimeError) as exc:
        return PairResult(ref.id.key, str(ref.id), "failed", seed, spent, message=_failure(exc))
    result = _write_one(job, ref, seed, pair, particles, rendered, 0, second=second)
    result.seconds = spent + time.perf_counter() - start
    return result


@dataclass
class _FirstFrame:
    """The first frame of a pair, rendered alone (see :func:`_sequence_pair`)."""

    image1: torch.Tensor
    opacity1: torch.Tensor
    image2: Optional[torch.Tensor] = None
    opacity2: Optional[torch.Tensor] = None


def _write_one(job: RenderJob, ref: PairRef, seed: int, pair, particles, rendered, index: int,
               second: bool = True) -> PairResult:
    frames = tuple(img[index].permute(1, 2, 0).cpu().numpy()
                   for img in (rendered.image1, rendered.image2) if img is not None)
    opacity = tuple(a[index, 0].cpu().numpy()
                    for a in (rendered.opacity1, rendered.opacity2) if a is not None)
    visible, few = visibility_of(pair, particles)
    seeds = (layer_seeds(job.preset, job.seed, ref.id)
             if isinstance(particles, LayeredParticles) else None)
    meta = pair_metadata(particles, ref.id, seed, job.preset.to_dict(), job.preset_name, seeds,
                         scaling=weather_scaling(job.preset, pair, job.particles_from))
    meta["visible1"], meta["visible2"] = (np.array(v, np.int64) for v in visible)
    out = pair_output(job, ref)
    right = None
    if job.stereo:
        try:
            right = _render_right(job, pair, particles, second)
        except WeatherGenError as exc:
            return PairResult(ref.id.key, str(ref.id), "failed", seed, message=str(exc))
    truth = particle_truth(pair, particles) if job.truth else None
    try:
        files = write_pair_outputs(out, pair, frames, opacity, meta, truth, second=second,
                                   right=right)
    except OSError as exc:   # a full or unwritable disk stops the run: every pair would fail
        raise write_error(exc, job.out, "then rerun with ${resume}") from None
    facts = dict(getattr(pair, "meta", None) or {})
    warnings = list(facts.pop("warnings", []))
    return PairResult(ref.id.key, str(ref.id), "written", seed,
                      bytes=sum(p.stat().st_size for p in files), visible=visible,
                      few_in_frame2=few,
                      particles=particles.count, input=jsonable(facts), warnings=warnings)


def _render_right(job: RenderJob, pair, particles, second: bool) -> RightView:
    """The right camera's outputs (the first frame, and the second when ``second``): the same
    particles seen from the dataset's second camera, occluded by its forward-warped depth, with
    that depth, its opacity and its cameras (in the left camera files' world)."""
    rc = right_camera(job.dataset, pair)
    _, c1, c2 = reference_transforms(pair)
    k_right = pair.intrinsics if rc.intrinsics is None else rc.intrinsics
    count = 2 if second else 1
    layered = isinstance(particles, LayeredParticles)
    views, kinds, left_kinds = [], [], (pair.depth_provenance1, pair.depth_provenance2)
    for depth, cam, kind in zip((pair.depth1, pair.depth2)[:count], (c1, c2), left_kinds):
        depth_r, kind_r = warp_view_depth(depth, kind, pair.intrinsics, rc.right_from_left, rc.intrinsics)
        views.append(stereo_view(View(pair.intrinsics, cam, depth), rc.right_from_left, depth_r, rc.intrinsics))
        kinds.append(kind_r)        # the right view's provenance (holes: their background's)
    with torch.no_grad():
        if layered:                     # each frame drawn from its own view
            rendered = zip(*render_right_layers((rc.image1, rc.image2)[:count], views,
                                                particles))
        else:
            lib = load_templates(particles.settings.templates)
            start1, start2, disp = pair_starts(particles, torch.float32, torch.device("cpu"))
            rendered = (render_right(image, view, particles, start, disp, lib, frame=t)
                        for t, (image, view, start) in enumerate(zip(
                            (rc.image1, rc.image2), views[:count], (start1, start2))))
        frames, opacity, depths, cams = [], [], [], []
        for (out, alpha), view in zip(rendered, views[:count]):
            frames.append(out.permute(1, 2, 0).numpy())
            opacity.append(alpha[0].numpy())
            depths.append(view.depth[0].numpy())
            cams.append(view.cam_from_ref.numpy())
    return RightView(tuple(frames), tuple(opacity), tuple(depths), k_right.double().numpy(), tuple(cams),
                     rc.right_from_left.double().numpy(), tuple(k[0].numpy() for k in kinds if k is not None))


# -- the run -------------------------------------------------------------------------------------
def run_render(job: RenderJob, on_result: Callable[[PairResult], None] = lambda r: None,
               on_start: Callable[[int], None] = lambda n: None,
               on_note: Callable[[str], None] = lambda text: None) -> list[PairResult]:
    """Render every selected pair of the job's shard; return one result per pair.

    Pairs already complete on disk are skipped when resuming (or when another shard's folder is
    reused). ``on_start`` receives the number of pairs, ``on_result`` each result as it arrives,
    ``on_note`` warnings worth a line (a stale lock taken over, a gap in a scene's frame
    numbering, a scene whose frames cannot be paired). Interruptions (Ctrl-C, SIGTERM) record
    what was finished in the manifest and re-raise. The output folder is locked for the run: a
    second run in it (same shard) raises :class:`~weathergen.errors.FolderBusy`.

    Raises :class:`~weathergen.errors.OutputError` when the outputs cannot be written (the pairs
    finished before are recorded), and :class:`~weathergen.errors.NothingRendered` when every
    selected pair fails (an output folder that this run created is removed again).
    """
    check_executor(job.executor)
    available_memory()          # a memory budget that is not an amount fails here
    every, refs = _selection(job, on_note)
    if job.sequence:
        _check_sequence_preset(job)
        # The pairs whose second frame starts no selected pair write both their frames.
        starts = {(r.id.dataset, r.id.split, r.id.scene, r.id.frame) for r in every}
        job.scene_ends = frozenset(r.id for r in every if (r.id.dataset, r.id.split, r.id.scene,
                                                           r.id.frame + 1) not in starts)
    job.scene_firsts = scene_firsts(every)
    with claim_folder(job.out, RENDER_FOLDER, job.config(), resume=job.resume,
                      overwrite=job.overwrite, shard=job.shard,
                      temporary=temporary_places(job, refs), on_note=on_note) as claim:
        results = _render_locked(job, refs, on_result, on_start, on_note)
        done = [r for r in results if r.status == "written"]
        for note in filter(None, (depth_note([(r.pair, r.input) for r in done]), frame2_note(
                [(r.pair, r.visible) for r in done if r.few_in_frame2], job.preset_name))):
            on_note(note)
        if results and all(r.status == "failed" for r in results):
            first = results[0]
            # the claim removes a folder it created again
            raise NothingRendered(f"every selected pair failed ({len(results)}; the first: "
                                  f"{first.pair}: {first.message}); "
                                  + ("nothing was written" if claim.created else
                                     f"the failures are recorded in {job.out / MANIFEST}"))
        return results


def _selection(job: RenderJob, on_note) -> tuple[list[PairRef], list[PairRef]]:
    """Every selected pair, and those of the job's shard; the dataset's notes go to ``on_note``.

    A root that is not of the chosen layout fails here, before the output folder is touched."""
    every = selected_pairs(job.dataset, job.particles_from, on_note)
    refs = shard_refs(every, job.shard)
    if not every:
        raise ConfigError(job.dataset.no_pairs_message())
    if not refs:
        raise ConfigError(f"${{shard}} {job.shard[0]}/{job.shard[1]} holds no frame pairs: the "
                          f"selection holds {len(every)}, one for each of the first {len(every)} "
                          f"shards")
    return every, refs


def _check_sequence_preset(job: RenderJob) -> None:
    """A sequence render needs weather-field presets in every layer: refuse a paper preset."""
    layers = job.preset.layers if isinstance(job.preset, CombinedPreset) else [job.preset]
    paper = [layer for layer in layers if not isinstance(layer, FieldPreset)]
    if paper and len(layers) > 1:
        raise ConfigError(f"sequence rendering needs weather-field presets in every layer "
                          f"(model = field, e.g. snow-moderate+fog-light); layer "
                          f"'{paper[0].name}' of '{job.preset_name}' is a paper preset, "
                          "whose particles belong to one pair")
    if paper:
        raise ConfigError(f"sequence rendering needs a weather-field preset (model = field, "
                          f"e.g. snow-moderate); '{job.preset_name}' is a paper preset, "
                          "whose particles belong to one pair")


def _render_locked(job: RenderJob, refs: list[PairRef], on_result, on_start,
                   on_note) -> list[PairResult]:
    started = time.time()
    t0 = time.perf_counter()
    results: list[PairResult] = []
    todo: list[PairRef] = []
    for ref in refs:
        if not job.overwrite and pair_output(job, ref).is_complete():
            results.append(PairResult(ref.id.key, str(ref.id), "skipped",
                                      weather_seed(job.preset, job.seed, ref.id)))
        else:
            todo.append(ref)
    on_start(len(refs))
    for r in results:
        on_result(r)
    if job.workers < 1:
        job = dataclasses.replace(job, workers=auto_workers(len(todo), job.device))
    stopped_by: Optional[BaseException] = None
    try:
        if job.executor == "ray":
            _run_ray(job, todo, results, on_result)
        elif job.workers <= 1 or len(todo) <= job.batch_size:
            threads = torch.get_num_threads()
            try:
                for chunk in _chunks(todo, job.batch_size):
                    for r in render_batch(job, chunk):
                        results.append(r)
                        on_result(r)
            finally:
                torch.set_num_threads(threads)
        else:
            _run_pool(job, todo, results, on_result, on_note)
    except BaseException as exc:
        stopped_by = exc
        raise
    finally:
        record_manifest(job, results, started, time.perf_counter() - t0, stopped_by)
    return results


def _chunks(items: list, size: int) -> list[list]:
    return [items[i:i + size] for i in range(0, len(items), max(1, size))]


def _run_ray(job, todo, results, on_result):
    # Each task renders one batch on the device it was given; the driver records the results.
    remote_job = replace(job, device=worker_device(job.device, "ray"))
    units = [(remote_job, chunk) for chunk in _chunks(todo, job.batch_size)]
    for batch in ray_map(render_batch, units, address=job.ray_address,
                         num_gpus=ray_gpus_for(job.device)):
        for r in batch:
            results.append(r)
            on_result(r)


def _run_pool(job, todo, results, on_result, on_note):
    """Render the chunks on a pool of worker processes, recording each result as it arrives.

    Ctrl-C and SIGTERM are held back while the pool runs (see :class:`StopRequests`): once one
    comes, no new chunk starts, the chunks already running finish, every result is recorded, and
    only then is the interruption passed on. Nothing a worker finished is left out of the record.

    A worker that dies (killed by the system when memory runs out, say) breaks the pool: the
    results that came in are kept, the other workers are stopped, and the chunks that were out
    (the dead worker's and the others') are rendered again, one at a time by a worker of their
    own, so that a chunk whose worker dies again is known to be the cause: it fails, its pairs
    saying how the worker ended. Then the rest goes on with every worker.
    """
    queue = _chunks(todo, job.batch_size)
    suspects: list = []
    with StopRequests() as stop:
        while (suspects or queue) and stop.signum is None:
            if suspects:                   # one at a time: a death names its chunk
                lost, ended = _pool_round(job, suspects, stop, results, on_result, workers=1)
                for refs in lost:
                    for ref in refs:
                        r = PairResult(ref.id.key, str(ref.id), "failed",
                                       weather_seed(job.preset, job.seed, ref.id),
                                       message=f"its worker process died twice, the second time "
                                               f"rendering it alone ({ended}); render it with "
                                               f"--workers 1 to see why")
                        results.append(r)
                        on_result(r)
                continue
            suspects, ended = _pool_round(job, queue, stop, results, on_result, job.workers)
            if suspects and stop.signum is None:
                pairs = sum(len(refs) for refs in suspects)
                on_note(f"a worker process died ({ended}); the {counted(pairs, 'pair')} it and "
                        "the other workers had in hand are rendered again, one batch at a time")


def _pool_round(job, queue: list, stop: StopRequests, results, on_result,
                workers: int) -> tuple[list, str]:
    """Hand the chunks of ``queue`` to one pool of ``workers`` workers until it is empty, a stop
    is requested or a worker dies. Returns the chunks that were out when a worker died (none
    otherwise) and how the dead worker ended; chunks never handed out stay in ``queue``."""
    ctx = multiprocessing.get_context("spawn")
    before = set(multiprocessing.active_children())
    started: set = set()
    out: dict = {}                         # future -> (position, chunk)
    pending: set = set()
    lost: list = []
    broken = False                         # a worker died (idle ones too: submit refuses then)
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=init_worker,
                               initargs=(os.getpid(),))
    try:
        while pending or (queue and stop.signum is None and not broken):
            while queue and stop.signum is None and not broken and len(pending) < 2 * workers:
                if workers == 1 and pending:
                    break                  # one at a time
                try:
                    with spawning():       # the pool starts its workers on demand, in submit
                        fut = pool.submit(render_batch, job, queue[0])
                except BrokenProcessPool:
                    broken = True          # the loop below collects the chunks that were out
                    break
                out[fut] = (len(out), queue.pop(0))
                pending.add(fut)
                started |= set(multiprocessing.active_children()) - before
            done, pending = wait(pending, timeout=POLL_SECONDS, return_when=FIRST_COMPLETED)
            if stop.signum is not None:
                for fut in pending:
                    fut.cancel()           # not started yet: it stays undone (--resume renders it)
            for fut in sorted(done, key=lambda f: out[f][0]):
                if fut.cancelled():
                    continue
                if isinstance(fut.exception(), BrokenProcessPool):
                    lost.append(out[fut][1])
                    broken = True
                    continue
                for r in fut.result():
                    results.append(r)
                    on_result(r)
            if lost:                       # every future of a broken pool fails at once
                lost += [out[f][1] for f in pending]
                pending = set()
    finally:
        ended = _stop_workers(started) if broken else ""
        pool.shutdown(wait=True, cancel_futures=True)
    if lost:
        forget_lost(job, [ref for refs in lost for ref in refs])
    return lost, ended


def _stop_workers(workers: set) -> str:
    """After a worker died: how it ended, in words (:func:`~weathergen.workers.how_it_ended`);
    the workers still alive are killed (what they were rendering was lost with the pool, and a
    worker ignores the pool's own SIGTERM)."""
    time.sleep(POLL_SECONDS)               # the dead one is reaped, its exit code known
    dead = [p.exitcode for p in workers if p.exitcode not in (None, 0)]
    for p in workers:
        if p.exitcode is None:
            p.kill()
    for p in workers:
        p.join(timeout=10)
    return how_it_ended(dead[0]) if dead else "ended without a word"


#: How often the pool loop looks for a held-back Ctrl-C or SIGTERM (seconds).
POLL_SECONDS = 0.1


__all__ = ["RenderJob", "PairResult", "render_batch", "run_render"]
