"""One weather for a whole sequence, attacked: the world weather of a scene, optimised against
every pair of the scene at once.

A weather field (:mod:`weathergen.engine.sampling.field`) gives every pair of a scene its particles from
one periodic field: particle ``j`` of tile copy ``k`` (a *trajectory*) is at
``start_j + n step_j + k L`` in frame ``n``, and the pairs that see it share it. The attack frees
one value per trajectory of the scene (the union of its pairs' trajectories), per field layer:

- ``offset1``: an offset in the reference frame's axes (world metres on metric datasets) that
  moves the particle in every frame alike (a pair's record gets it as δ1, and δ2 stays zero, so
  frame 2 of one pair is frame 1 of the next);
- ``color`` and ``transparency``, in the atanh domains of the pair attack;
- ``density`` and ``airlight``: the layer's atmosphere, fixed in the world, one for the scene.

A pair's record is the scene's current values at the pair's own trajectories, so every frame
shows what ``render --sequence`` renders of that weather, and the written particle files
re-render with ``render --particles``. The parametrisation is the pair attack's
(:class:`~weathergen.attack.pair.WeatherVariables` of the scene's record); each pair is
evaluated by a :class:`~weathergen.attack.pair.BatchOptimisation` whose variables are the pair's
views of the scene's. The loss is the mean over pairs of the paper's loss of each pair (distance
to its target plus the offset penalty at its own depths); pairs are evaluated ``chunk`` at a time
and their gradients added, then Adam takes one step (one group per learning-rate group). The
best step is the one with the lowest mean distance over the scene's pairs: one weather for all.
``offset2`` (a move in frame 2 alone) and ``compat="reference"`` (the research code attacks
pairs) have no place here and are refused. With each pair's second camera
(:class:`SecondView`, stereo), the same weather is drawn into its frames as ``render --stereo``
draws it, and each pair's loss adds that camera's distance to its target.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch

from ..engine import (CombinedPreset, FieldPreset, LayeredParticles, View, field_for_pair,
                      field_record, load_templates, pair_trajectories, pair_views,
                      reference_transforms)
from ..engine.rendering.stereo import render_right, render_right_layers, stereo_view, warp_view_depth
from ..engine.rendering.tracks import pair_starts
from ..datasets import right_camera
from ..errors import ConfigError
from ..flow import aee
from ..framepair import FramePair
from ..jobs import layer_seeds, scene_airlight, weather_seed
from .figures import written_flow
from .pair import BatchOptimisation, LayeredVariables, WeatherVariables, attack_batch, snapshot
from .rates import group_optimizer
from .settings import AttackSettings
from .steps import AttackResult, StepLog, StepRecord
from .targets import TargetSpec, target_flow

#: The variables of one world weather.
SEQUENCE_VARIABLES = ("offset1", "color", "transparency", "density", "airlight")


def check_sequence_preset(preset, name: str) -> None:
    """Refuse a preset whose particles belong to one pair (a paper preset, or a combined preset
    with a paper layer): a world weather is a weather field's."""
    layers = preset.layers if isinstance(preset, CombinedPreset) else (preset,)
    paper = [layer.name for layer in layers if not isinstance(layer, FieldPreset)]
    if paper:
        which = f"'{name}' is" if len(layers) == 1 else f"layer '{paper[0]}' of '{name}' is"
        raise ConfigError(f"${{sequence}} attacks one weather field over whole scenes (e.g. "
                          f"snow-moderate, fog-heavy, rain-heavy+fog-light); {which} a paper "
                          f"preset, whose particles belong to one pair")


def check_sequence_settings(settings: AttackSettings) -> None:
    """Refuse what a world weather cannot be: a move in frame 2 alone, the research code's terms."""
    if "offset2" in settings.optimize:
        raise ConfigError("${optimize} offset2 moves a particle in frame 2 alone; one weather for "
                          "a sequence has one position per particle and frame: free offset1")
    if settings.compat != "paper":
        raise ConfigError("${compat} reference: the research code attacks pairs, not sequences")
    if settings.early_stop is not None:
        raise ConfigError("${early_stop}: a sequence attack runs every step (one weather for "
                          "all the scene's pairs, whose losses converge apart)")


@dataclass
class SceneWeather:
    """A scene's weather as trajectories: ``world`` one record of every trajectory of the scene
    (a :class:`~weathergen.engine.LayeredParticles` for combined weather, one layer per field),
    ``index[p][i]`` (M,) the position in layer ``i`` of ``world`` of each particle of pair ``p``'s
    record (its order; ``index[p]`` alone for one layer)."""

    world: object
    index: list


def _unique_rows(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Sorted unique rows of an (M, 4) integer tensor and the index of each row among them."""
    if rows.shape[0] == 0:
        return rows, torch.zeros(0, dtype=torch.long)
    return torch.unique(rows, dim=0, return_inverse=True)


def scene_weather(pairs: Sequence[FramePair], records: Sequence, preset, seeds: Sequence, *,
                  world_up: str = "auto", frame_rate: Optional[float] = None,
                  airlight=None) -> SceneWeather:
    """The :class:`SceneWeather` of a scene's pairs and their sampled ``records`` (as
    :func:`~weathergen.jobs.pair_particles` gives them): ``seeds[p]`` pair ``p``'s field seed (a
    tuple of one per layer for a combined preset), ``world_up``, ``frame_rate`` and ``airlight``
    as the records were sampled with. Raises ConfigError when the pairs' fields differ (cameras
    without a shared world) or a record is not its field's."""
    layered = isinstance(preset, CombinedPreset)
    layers = preset.layers if layered else (preset,)
    found: list[list] = [[] for _ in layers]          # per layer, per pair: (j, k), frame
    fields = []
    for p, pair in enumerate(pairs):
        seed = seeds[p] if layered else (seeds[p],)
        n = int(pair.id.frame)
        views = pair_views(pair)
        for i, (layer, s) in enumerate(zip(layers, seed)):
            fld = field_for_pair(pair, layer, s, world_up=world_up, frame_rate=frame_rate,
                                 airlight=airlight)
            if p == 0 and fld.frame == "world":
                fields.append(fld)
            elif (fld.frame != "world" or not torch.equal(fld.start, fields[i].start)
                  or not torch.equal(fld.step, fields[i].step)):
                raise ConfigError(f"{pair.id}: its weather field is not the scene's (the "
                                  f"sequence attack needs cameras posed in one world)")
            j, k = pair_trajectories(fld, views, (n, n + 1))
            count = (records[p].layers[i] if layered else records[p]).count
            if int(j.numel()) != count:
                raise ConfigError(f"{pair.id}: its particles are not its weather field's")
            found[i].append((j, k))
    world, index = [], [[None] * len(layers) for _ in pairs]
    for i, per_pair in enumerate(found):
        rows = torch.cat([torch.cat((j[:, None], k), 1) for j, k in per_pair])
        unique, inverse = _unique_rows(rows)
        start = 0
        for p, (j, _) in enumerate(per_pair):
            index[p][i] = inverse[start:start + j.numel()]
            start += j.numel()
        world.append(field_record(fields[i], unique[:, 0], unique[:, 1:],
                                  int(pairs[0].id.frame)))
    if layered:
        return SceneWeather(LayeredParticles(tuple(world), records[0].names), index)
    return SceneWeather(world[0], [i[0] for i in index])


def _pair_record(base, world, index: torch.Tensor, optimize: tuple[str, ...]):
    """One layer's record of a pair: ``base`` with the freed fields taken from the scene's
    current ``world`` record at the pair's trajectories ``index``."""
    changes = {name: getattr(world, name)[index] for name in ("offset1", "color", "transparency")
               if name in optimize}
    if base.atmosphere is not None and world.atmosphere is not None:
        air = {name: getattr(world.atmosphere, name) for name in ("density", "airlight")
               if name in optimize}
        changes["atmosphere"] = base.atmosphere.replace(**air)
    return base.replace(**changes)


class PairView:
    """A pair's particles as a view of the scene's variables: what a
    :class:`~weathergen.attack.pair.BatchOptimisation` asks of its variables (``particles()``;
    its own freed variables are the scene's, optimised outside it)."""

    def __init__(self, scene, base, index, optimize: tuple[str, ...]):
        self.scene, self.base, self.index, self.optimize = scene, base, index, optimize

    def particles(self):
        world = self.scene.particles()
        if not isinstance(self.base, LayeredParticles):
            return _pair_record(self.base, world, self.index, self.optimize)
        out = self.base
        for k in self.scene.freed:
            out = out.replace_layer(k, _pair_record(self.base.layers[k], world.layers[k],
                                                    self.index[k], self.optimize))
        return out

    def parameters(self) -> list:
        return []

    def atmosphere_parameters(self) -> list:
        return []


def _runs(model, pairs, particles, weather: SceneWeather, settings, target, device,
          target_file_flow, chunk: int):
    """The pairs' evaluations, ``chunk`` pairs each, their variables the scene's; and those."""
    runs = [BatchOptimisation(model, pairs[i:i + chunk], particles[i:i + chunk], settings,
                              target, device=device, target_file_flow=target_file_flow)
            for i in range(0, len(pairs), chunk)]
    world = weather.world.to(device=runs[0].frames["image1"].device, dtype=torch.float32)
    scene = (LayeredVariables(world, settings.optimize, layers=settings.layers,
                              transparency_max=settings.transparency_max)
             if isinstance(world, LayeredParticles) else
             WeatherVariables(world, settings.optimize, transparency_max=settings.transparency_max))
    p = 0
    for run in runs:
        views = []
        for v in run.variables:
            views.append(PairView(scene, v.base, weather.index[p], settings.optimize))
            p += 1
        run.variables = views
    return runs, scene


@dataclass
class SecondView:
    """A pair's second (right) camera: its clean frames 1 and 2, (3, H, W) each, and its
    :class:`~weathergen.engine.View` of each (occluded by the left depth warped into it)."""

    images: tuple
    views: tuple


def second_view(pair: FramePair, camera) -> SecondView:
    """The :class:`SecondView` of a pair from its dataset's right camera
    (:func:`~weathergen.datasets.right_camera`), as ``render --stereo`` draws it."""
    _, c1, c2 = reference_transforms(pair)
    views = []
    for depth, cam, kind in zip((pair.depth1, pair.depth2), (c1, c2),
                                (pair.depth_provenance1, pair.depth_provenance2)):
        right_depth, _ = warp_view_depth(depth, kind, pair.intrinsics, camera.right_from_left,
                                         camera.intrinsics)
        views.append(stereo_view(View(pair.intrinsics, cam, depth), camera.right_from_left,
                                 right_depth, camera.intrinsics))
    return SecondView((camera.image1, camera.image2), tuple(views))


def second_frames(record, second: SecondView, beta: float) -> list[torch.Tensor]:
    """The second camera's weather frames 1 and 2 of a pair's record, differentiable in it, as
    ``render --stereo`` draws them. Shape: -> two (3, H, W)."""
    if isinstance(record, LayeredParticles):
        return render_right_layers(second.images, second.views, record, beta=beta)[0]
    lib = load_templates(record.settings.templates)
    device = second.images[0].device
    start1, start2, moved = pair_starts(record, torch.float32, device)
    return [render_right(image, view, record, start, moved, lib, beta=beta, frame=t)[0]
            for t, (image, view, start) in enumerate(zip(second.images, second.views,
                                                         (start1, start2)))]


class _Seconds:
    """The second cameras of one evaluation's pairs: their clean flow and goal, and their
    distance to the goal under the pairs' current records."""

    def __init__(self, model, seconds: Sequence[SecondView], target, target_file_flow, beta,
                 device):
        self.model, self.beta = model, beta
        self.seconds = [SecondView(tuple(i.to(device) for i in s.images), tuple(
            View(v.intrinsics.to(device), v.cam_from_ref.to(device), v.depth.to(device))
            for v in s.views)) for s in seconds]
        with torch.no_grad():
            self.benign = model(*(torch.stack([s.images[t] for s in self.seconds])
                                  for t in (0, 1)))
        self.goal = target_flow(target, self.benign, target_file_flow)

    def distances(self, records) -> tuple[torch.Tensor, torch.Tensor]:
        """(B,) distances to the goal, with gradient, and the flow (B, 2, H, W)."""
        frames = [second_frames(r, s, self.beta) for r, s in zip(records, self.seconds)]
        flow = self.model(*(torch.stack([f[t] for f in frames]) for t in (0, 1)))
        return aee(flow, self.goal), flow


def _evaluate(run, seconds, scale: float, backward: bool) -> dict:
    """One evaluation of a chunk of pairs (and their second cameras): the terms of the steps'
    log, detached, after adding the gradient of ``scale`` times their losses."""
    records, flow, loss, distance, penalty = run.evaluate()
    total = loss.sum()
    out = {"records": records, "depends": run.depends}
    if seconds is not None:
        far, second_flow = seconds.distances(records)
        total = total + far.sum()
        out.update(second=far.detach(), second_flow=second_flow.detach())
    if backward and any(run.depends):
        (total * scale).backward()
    out.update(flow=flow.detach(), loss=loss.detach(), distance=distance.detach(),
               penalty=penalty.detach())
    return out


def attack_sequence(model: torch.nn.Module, pairs: Sequence[FramePair], particles: Sequence,
                    weather: SceneWeather, settings: AttackSettings,
                    target: TargetSpec = TargetSpec("zero"), *, device=None,
                    target_file_flow: Optional[torch.Tensor] = None, chunk: int = 1,
                    seconds: Optional[Sequence[SecondView]] = None,
                    on_step: Callable[[int, StepRecord], None] = lambda i, r: None
                    ) -> list[AttackResult]:
    """Optimise one weather for the pairs of a scene (see the module doc).

    Args: as :func:`~weathergen.attack.attack_batch`, and ``weather`` (:func:`scene_weather` of
    these pairs and records), ``chunk`` the pairs evaluated in one forward pass, ``seconds``
    each pair's :class:`SecondView` (stereo: the loss and the best step then take both cameras'
    distances, averaged).
    Returns: one :class:`~weathergen.attack.AttackResult` per pair, all with the scene's best step
    (each pair's record there, its history and flows: the left camera's); with ``seconds``,
    each result's ``second`` holds the second camera's ``benign``, ``initial`` and ``best``
    flows (float frames).
    """
    check_sequence_settings(settings)
    pairs, particles, n = list(pairs), list(particles), max(1, int(chunk))
    runs, scene = _runs(model, pairs, particles, weather, settings, target, device,
                        target_file_flow, n)
    twins = [None] * len(runs) if seconds is None else [
        _Seconds(model, seconds[i * n:(i + 1) * n], target, target_file_flow, settings.beta,
                 run.frames["image1"].device) for i, run in enumerate(runs)]
    optimizer = group_optimizer([scene], settings)
    size, steps, views = len(pairs), int(settings.steps), 1 if seconds is None else 2
    log, keep = StepLog(size, on_step), {}
    benign = torch.cat([run.benign for run in runs])
    for step in range(steps + 1):
        t0 = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        parts = [_evaluate(run, twin, 1 / (size * views), step < steps)
                 for run, twin in zip(runs, twins)]
        joined = {k: torch.cat([p[k] for p in parts]) for k in parts[0] if k not in
                  ("records", "depends")}
        dists = joined["distance"].cpu().tolist()
        score = (sum(dists) + (float(joined["second"].sum()) if seconds else 0)) / (size * views)
        if step == 0:
            keep["initial"] = joined
        if score < keep.get("score", math.inf):
            keep.update(score=score, best=joined, records=[snapshot(r) for p in parts
                                                            for r in p["records"]])
            for i in range(size):
                log.best[i], log.best_step[i] = dists[i], step
                log.best_flow[i] = joined["flow"][i:i + 1].cpu()
        log.record(step, range(size), joined["flow"], benign, joined["loss"], dists,
                   joined["penalty"], t0)
        frozen = not any(d for p in parts for d in p["depends"])
        if step == steps or frozen:
            break
        optimizer.step()
    return _results(runs, twins, log, keep, frozen)


def _results(runs, twins, log: StepLog, keep: dict, frozen: bool) -> list[AttackResult]:
    benign = torch.cat([run.benign for run in runs]).cpu()
    goal = torch.cat([run.goal for run in runs]).cpu()
    initial = keep["initial"]["flow"].cpu()
    results = [AttackResult(best_particles=keep["records"][i], best_step=log.best_step[i],
                            history=log.history[i], benign_flow=benign[i:i + 1],
                            initial_flow=initial[i:i + 1], best_flow=log.best_flow[i],
                            target=goal[i:i + 1], frozen=frozen) for i in range(len(benign))]
    if twins[0] is not None:
        second = torch.cat([t.benign for t in twins]).cpu()
        first, best = keep["initial"]["second_flow"].cpu(), keep["best"]["second_flow"].cpu()
        for i, result in enumerate(results):
            result.second = {"benign": second[i:i + 1], "initial": first[i:i + 1],
                             "best": best[i:i + 1]}
    return results


def scene_units(refs: Sequence) -> list[list]:
    """The pairs (:class:`~weathergen.datasets.PairRef`) grouped by scene, in their order: the
    work units of a sequence attack."""
    units: dict[tuple, list] = {}
    for ref in refs:
        units.setdefault((ref.id.dataset, ref.id.split, ref.id.scene), []).append(ref)
    return list(units.values())


#: The figures of a sequence attack's summary per scene.
SCENE_FIGURES = ("aee_random", "aee_adversarial", "per_pair_aee_adversarial", "target_initial",
                 "target_adversarial", "per_pair_target_adversarial", "second_aee_random",
                 "second_aee_adversarial")


def scene_figures(rows: Sequence) -> dict:
    """The means of :data:`SCENE_FIGURES` over each scene's pairs
    (:class:`~weathergen.attack.PairSummary` rows), by scene (``dataset/split/scene``)."""
    scenes: dict[str, list] = {}
    for row in rows:
        scenes.setdefault(row.pair.rsplit("/", 1)[0], []).append(row)
    out = {}
    for scene, members in scenes.items():
        figures = {"pairs": len(members)}
        for key in SCENE_FIGURES:
            values = [getattr(r, key) for r in members if getattr(r, key) is not None]
            figures[key] = sum(values) / len(values) if values else None
        out[scene] = figures
    return out


def sequence_results(job, model, pairs: list, particles: list, device,
                     target_file_flow, on_step) -> tuple[list, list]:
    """A scene's pairs (of an :class:`~weathergen.attack.AttackJob`, ``job``) attacked with one
    weather (:func:`attack_sequence`, ``job.batch_size`` pairs per forward pass), and each pair
    alone with the same settings and start (:func:`~weathergen.attack.attack_batch`), for
    comparison."""
    combined = isinstance(job.preset, CombinedPreset)
    seeds = [layer_seeds(job.preset, job.seed, p.id) if combined
             else weather_seed(job.preset, job.seed, p.id) for p in pairs]
    weather = scene_weather(pairs, particles, job.preset, seeds,
                            world_up=getattr(job.dataset, "world_up", "auto"),
                            frame_rate=job.dataset.frame_rate,
                            airlight=scene_airlight(job.dataset, pairs[0].id, job.scene_firsts,
                                                    job.preset))
    options = dict(device=device, target_file_flow=target_file_flow)
    seconds = ([second_view(p, right_camera(job.dataset, p)) for p in pairs] if job.stereo
               else None)
    results = attack_sequence(model, pairs, particles, weather, job.settings, job.target,
                              chunk=job.batch_size, seconds=seconds, on_step=on_step, **options)
    n = job.batch_size
    alone = [r for i in range(0, len(pairs), n)
             for r in attack_batch(model, pairs[i:i + n], particles[i:i + n], job.settings,
                                   job.target, **options)]
    return results, alone


def compare_alone(job, model, pair, result, alone, summary, device) -> None:
    """Set a sequence attack's pair's figures (its :class:`~weathergen.attack.PairSummary`) of the
    pair attacked alone (``alone``, its
    :class:`~weathergen.attack.AttackResult`), measured as the written ones, and of the second
    camera where ``result`` has one (float frames)."""
    flow = written_flow(model, pair, alone.best_particles, job.settings.beta, device)[3]
    summary.per_pair_aee_adversarial = float(aee(flow, alone.benign_flow).mean())
    summary.per_pair_target_adversarial = float(aee(flow, alone.target).mean())
    if result.second is not None:
        flows = result.second
        summary.second_aee_random = float(aee(flows["initial"], flows["benign"]).mean())
        summary.second_aee_adversarial = float(aee(flows["best"], flows["benign"]).mean())
