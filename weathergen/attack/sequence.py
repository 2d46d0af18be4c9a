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
pairs) have no place here and are refused.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch

from ..engine import (CombinedPreset, FieldPreset, LayeredParticles, field_for_pair, field_record,
                      pair_trajectories, pair_views)
from ..errors import ConfigError
from ..framepair import FramePair
from .pair import (AttackResult, BatchOptimisation, LayeredVariables, StepLog, StepRecord,
                   WeatherVariables, group_optimizer, snapshot)
from .settings import AttackSettings
from .targets import TargetSpec

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


def _scene_variables(world, settings: AttackSettings, device):
    world = world.to(device=device, dtype=torch.float32)
    options = dict(transparency_max=settings.transparency_max)
    if isinstance(world, LayeredParticles):
        return LayeredVariables(world, settings.optimize, layers=settings.layers, **options)
    return WeatherVariables(world, settings.optimize, **options)


def _runs(model, pairs, particles, weather: SceneWeather, settings, target, device,
          target_file_flow, chunk: int):
    """The pairs' evaluations, ``chunk`` pairs each, their variables the scene's; and those."""
    runs = [BatchOptimisation(model, pairs[i:i + chunk], particles[i:i + chunk], settings,
                              target, device=device, target_file_flow=target_file_flow)
            for i in range(0, len(pairs), chunk)]
    scene = _scene_variables(weather.world, settings, runs[0].frames["image1"].device)
    p = 0
    for run in runs:
        views = []
        for v in run.variables:
            views.append(PairView(scene, v.base, weather.index[p], settings.optimize))
            p += 1
        run.variables = views
    return runs, scene


def attack_sequence(model: torch.nn.Module, pairs: Sequence[FramePair], particles: Sequence,
                    weather: SceneWeather, settings: AttackSettings,
                    target: TargetSpec = TargetSpec("zero"), *, device=None,
                    target_file_flow: Optional[torch.Tensor] = None, chunk: int = 1,
                    on_step: Callable[[int, StepRecord], None] = lambda i, r: None
                    ) -> list[AttackResult]:
    """Optimise one weather for the pairs of a scene (see the module doc).

    Args: as :func:`~weathergen.attack.attack_batch`, and ``weather`` (:func:`scene_weather` of
    these pairs and records), ``chunk`` the pairs evaluated in one forward pass.
    Returns: one :class:`~weathergen.attack.AttackResult` per pair, all with the scene's best step
    (each pair's record there, its history, its flows).
    """
    check_sequence_settings(settings)
    pairs, particles = list(pairs), list(particles)
    runs, scene = _runs(model, pairs, particles, weather, settings, target, device,
                        target_file_flow, max(1, int(chunk)))
    optimizer = group_optimizer([scene], settings)
    size, steps = len(pairs), int(settings.steps)
    log = StepLog(size, on_step)
    best, best_particles, initial = math.inf, [None] * size, [None] * size
    benign = torch.cat([run.benign for run in runs])
    frozen = False
    for step in range(steps + 1):
        t0 = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        current, flows, losses, distances, penalties, depends = [], [], [], [], [], []
        for run in runs:
            records, flow, loss, distance, penalty = run.evaluate()
            if step < steps and any(run.depends):
                (loss.sum() / size).backward()
            current += records
            flows.append(flow.detach())
            losses.append(loss.detach())
            distances.append(distance.detach())
            penalties.append(penalty.detach())
            depends += run.depends
        flow, dists = torch.cat(flows), torch.cat(distances).cpu().tolist()
        if step == 0:
            initial = [flow[i:i + 1].cpu() for i in range(size)]
        if sum(dists) / size < best:
            best = sum(dists) / size
            for i in range(size):
                log.best[i], log.best_step[i] = dists[i], step
                log.best_flow[i] = flow[i:i + 1].cpu()
                best_particles[i] = snapshot(current[i])
        log.record(step, range(size), flow, benign, torch.cat(losses), dists,
                   torch.cat(penalties), t0)
        frozen = not any(depends)
        if step == steps or frozen:
            break
        optimizer.step()
    goal = torch.cat([run.goal for run in runs]).cpu()
    return [AttackResult(best_particles=best_particles[i], best_step=log.best_step[i],
                         history=log.history[i], benign_flow=benign[i:i + 1].cpu(),
                         initial_flow=initial[i], best_flow=log.best_flow[i],
                         target=goal[i:i + 1], frozen=frozen) for i in range(size)]


def scene_units(refs: Sequence) -> list[list]:
    """The pairs (:class:`~weathergen.datasets.PairRef`) grouped by scene, in their order: the
    work units of a sequence attack."""
    units: dict[tuple, list] = {}
    for ref in refs:
        units.setdefault((ref.id.dataset, ref.id.split, ref.id.scene), []).append(ref)
    return list(units.values())


#: The figures of a sequence attack's summary per scene.
SCENE_FIGURES = ("aee_random", "aee_adversarial", "per_pair_aee_adversarial", "target_initial",
                 "target_adversarial", "per_pair_target_adversarial")


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
