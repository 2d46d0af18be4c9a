"""Adversarial weather: optimise particle offsets, colours and transparencies against a flow network.

This module owns the optimisation loop of the paper's Section 3.2 and nothing else: tensors in,
tensors out, no file I/O (the job runner in :mod:`weathergen.attack.job` reads and writes).

The free variables (all start at zero, so step 0 is the random, unoptimised weather):

- ``offset1`` Δ1 (N, 3) and ``offset2`` Δ2 (N, 3), added to the record's offsets δ1, δ2 (scene
  units; δ1 moves the particle before its motion, δ2 after it). As in the paper's equations
  ``p1 = P (X1 + δ1)`` and ``p2 = P (T_rel (X1 + δ1) + (m + δ2))``, Δ1 is expressed in camera-1
  axes and Δ2 in camera-2 axes; the record's offsets live in its reference frame's axes, so the
  record gets ``R_ref←cam1 Δ1`` and ``R_ref←cam2 Δ2`` (norms, and so the penalty, are the same
  in both; Adam, being elementwise, is not indifferent to the axes);
- ``color`` (N, 3) and ``transparency`` (N,), offsets in the unbounded atanh domain
  ``η = atanh(2ξ − 1)``: the particle gets ``ξ = from_atanh(η0 + Δ)``, which can never leave
  (0, 1) (Carlini–Wagner box trick). Transparency is ``θ = θ_max ξ`` with the preset's bound
  ``θ_max`` (:func:`~weathergen.attack.settings.transparency_bound`: 1, or more for presets such
  as sparks whose θ exceeds 1), never below the record's own largest θ.

Loss (pixels)::

    L = AEE(f̌, f_target) + Σ_t α_t / |P| Σ_j ‖δ_t^j‖² / d_t^j

with ``f̌`` the flow on the weather frames, ``δ_t`` the particle's total offset and ``d_t`` its
camera depth in frame ``t`` before the attack (fixed, and clamped to at least
:data:`MIN_REG_DEPTH` for particles behind one of the cameras, which would otherwise flip the
sign of the penalty). Optimiser: Adam. Every step is measured; the step with the lowest
``AEE(f̌, f_target)`` (the *distance to the target*) is kept.

``AttackSettings.compat = "reference"`` swaps several of these terms for what the authors' research
code does (gradients accumulated over the steps, the occlusion detached, the penalty divided by the
squared frame-1 depth, a homogeneous component of δ1, the transparency bound, the figures); see
:mod:`weathergen.attack.compat`.

The gradient is the network's own: for RAFT that is the graph of the original implementation,
which detaches the flow estimate between refinement steps (``RAFTModel.detach_flow``, on by
default). The paper attacked those implementations, so its figures come from this truncated
gradient; it still reaches every image pixel through the correlation lookups and the context
features, and points close to the full one (cosine about 0.9 on the demo scene, with a similar
distance reached after a few steps). Set ``model.detach_flow = False`` for the full gradient.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Optional, Sequence

import torch

from ..engine import (LayeredParticles, build_stamps, from_atanh, load_templates,
                      reference_transforms, render, to_atanh)
from ..engine.records.particles import TENSOR_FIELDS
from ..engine.sampling.pair import check_pair_for_engine
from ..errors import ConfigError
from ..flow import aee
from ..framepair import FramePair
from ..geometry import transform_points
from .compat import (camera_translation_in_reference, detaches_occlusion,
                     reference_offset_penalty, resets_gradients)
from .rates import group_optimizer
from .settings import DEFAULT_ALPHA, DENSITY_FACTOR, AttackSettings
from .steps import AttackResult, StepLog, StepRecord
from .targets import TargetSpec, target_flow

#: Smallest particle depth (scene units) used in the offset penalty.
MIN_REG_DEPTH = 1e-3

# -- the parametrisation --------------------------------------------------------------------------

class WeatherVariables:
    """The attack's free variables and the map from them to a differentiable particle record.

    Args:
        particles: the starting record (N particles); any device, float fields float32.
        optimize: which of :data:`OPTIMIZABLE` to free.
        cam1_from_ref, cam2_from_ref: (4, 4) the cameras' transforms from the record's reference
            frame; the offset variables live in these cameras' axes (None: the reference axes).
        transparency_max: the largest θ the attack may reach (None: 1); never below the
            record's largest θ.
        homogeneous: also free ``offset1_w`` (N,), the research code's homogeneous component of
            δ1: it moves the frame-2 position by ``offset1_w`` times the camera translation
            (folded into the record's ``offset2``, which only frame 2 sees). Needs ``offset1``
            freed and both cameras.
    The record's other fields (positions, motions, templates, ...) stay fixed.
    """

    def __init__(self, particles, optimize: tuple[str, ...], *,
                 cam1_from_ref: Optional[torch.Tensor] = None,
                 cam2_from_ref: Optional[torch.Tensor] = None,
                 transparency_max: Optional[float] = None, homogeneous: bool = False):
        self.base = particles
        self.optimize = tuple(optimize)
        dev, dtype = particles.position.device, particles.position.dtype
        n = particles.count
        largest = float(particles.transparency.max()) if n else 0.0
        self.theta_max = max(1.0 if transparency_max is None else float(transparency_max), largest)
        self.eta_color = to_atanh(particles.color.detach())
        self.eta_theta = to_atanh(particles.transparency.detach() / self.theta_max)
        # Rows Δ (N, 3) in camera axes -> rows in reference axes: Δ R with R = cam_from_ref[:3, :3]
        # (a reference vector is Rᵀ Δ).
        eye = torch.eye(4, dtype=torch.float64)
        c1 = eye if cam1_from_ref is None else cam1_from_ref.detach().double().cpu()
        c2 = eye if cam2_from_ref is None else cam2_from_ref.detach().double().cpu()
        self.axes1 = c1[:3, :3].to(device=dev, dtype=dtype)
        self.axes2 = c2[:3, :3].to(device=dev, dtype=dtype)
        shapes = {"offset1": (n, 3), "offset2": (n, 3), "color": (n, 3), "transparency": (n,)}
        self.delta = {name: torch.zeros(shapes[name], dtype=dtype, device=dev, requires_grad=True)
                      for name in self.optimize if name in shapes}
        self.atmosphere = {}          # the atmosphere's freed variables (none without one)
        atm = particles.atmosphere
        if atm is not None:
            if "density" in self.optimize:
                self.rho_density = atm.lattice(dtype, dev).detach()
                self.atmosphere["density"] = torch.zeros_like(self.rho_density,
                                                              requires_grad=True)
            if "airlight" in self.optimize:
                self.eta_airlight = to_atanh(atm.airlight.detach().to(device=dev, dtype=dtype))
                self.atmosphere["airlight"] = torch.zeros(3, dtype=dtype, device=dev,
                                                          requires_grad=True)
        if homogeneous and "offset1" in self.optimize:
            self.translation = camera_translation_in_reference(c1, c2).to(device=dev, dtype=dtype)
            self.delta["offset1_w"] = torch.zeros(n, dtype=dtype, device=dev, requires_grad=True)

    def parameters(self) -> list[torch.Tensor]:
        """The particles' freed variables (the atmosphere's: :meth:`atmosphere_parameters`)."""
        return list(self.delta.values())

    def atmosphere_parameters(self) -> list[torch.Tensor]:
        return list(self.atmosphere.values())

    def particles(self):
        """The current record; differentiable in the freed variables. Fixed fields are the
        starting record's tensors (a variable not optimised keeps its exact starting value)."""
        b, d = self.base, self.delta
        changes = {}
        if self.atmosphere:
            a = self.atmosphere
            air = {}
            if "density" in a:     # log space, within DENSITY_FACTOR of the sampled value
                bound = math.log(DENSITY_FACTOR)
                air["density"] = self.rho_density * torch.exp(
                    bound * torch.tanh(a["density"] / bound))
            if "airlight" in a:
                air["airlight"] = from_atanh(self.eta_airlight + a["airlight"])
            changes["atmosphere"] = b.atmosphere.replace(**air)
        if "offset1" in d:
            changes["offset1"] = b.offset1 + d["offset1"] @ self.axes1
        if "offset2" in d:
            changes["offset2"] = b.offset2 + d["offset2"] @ self.axes2
        if "offset1_w" in d:
            changes["offset2"] = changes.get("offset2", b.offset2) \
                + d["offset1_w"][:, None] * self.translation
        if "color" in d:
            changes["color"] = from_atanh(self.eta_color + d["color"])
        if "transparency" in d:
            changes["transparency"] = self.theta_max * from_atanh(self.eta_theta
                                                                  + d["transparency"])
        return b.replace(**changes)


class LayeredVariables:
    """The free variables of combined weather (:class:`~weathergen.engine.LayeredParticles`):
    a :class:`WeatherVariables` per freed layer (``layers`` by name, None: every layer), each
    with the keyword arguments of :class:`WeatherVariables`; the other layers stay as they are.
    """

    def __init__(self, particles: LayeredParticles, optimize: tuple[str, ...], *,
                 layers: Optional[Sequence[str]] = None, **options):
        self.base = particles
        chosen = particles.names if layers is None else tuple(layers)
        unknown = [n for n in chosen if n not in particles.names]
        if unknown:
            raise ConfigError(f"${{optimize_layer}} {', '.join(unknown)}: no such layer (layers: "
                              f"{', '.join(particles.names)})")
        indices = sorted({particles.index_of(n) for n in chosen})      # in the layers' order
        self.freed = {k: WeatherVariables(particles.layers[k], optimize, **options)
                      for k in indices}

    def parameters(self) -> list[torch.Tensor]:
        return [p for v in self.freed.values() for p in v.parameters()]

    def atmosphere_parameters(self) -> list[torch.Tensor]:
        return [p for v in self.freed.values() for p in v.atmosphere_parameters()]

    def particles(self) -> LayeredParticles:
        out = self.base
        for k, v in self.freed.items():
            out = out.replace_layer(k, v.particles())
        return out

    @property
    def delta(self) -> dict:
        """The freed layers' added offsets, joined (as :attr:`WeatherVariables.delta`)."""
        names = {n for v in self.freed.values() for n in v.delta}
        return {n: torch.cat([v.delta[n] for v in self.freed.values()]) for n in names}


def particle_depths(particles, cam1_from_ref: torch.Tensor, cam2_from_ref: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera depth of every particle in frame 1 (at P + δ1) and frame 2 (at P + δ1 + M + δ2).

    Shape: cam*_from_ref (4, 4); returns two (N,) tensors in scene units, clamped to at least
    :data:`MIN_REG_DEPTH`, without gradient.
    """
    with torch.no_grad():
        p = particles.position.double() + particles.offset1.double()
        q = p + particles.motion.double() + particles.offset2.double()
        z1 = transform_points(cam1_from_ref.double().to(p.device), p)[:, 2]
        z2 = transform_points(cam2_from_ref.double().to(p.device), q)[:, 2]
    dtype = particles.position.dtype
    return z1.clamp(min=MIN_REG_DEPTH).to(dtype), z2.clamp(min=MIN_REG_DEPTH).to(dtype)


def start_depth(particles, cam1_from_ref: torch.Tensor) -> torch.Tensor:
    """Frame-1 camera depth of every particle's starting position ``P + δ1``, unclamped and
    without gradient. Shape: cam1_from_ref (4, 4); returns (N,) in scene units."""
    with torch.no_grad():
        p = particles.position.double() + particles.offset1.double()
        z1 = transform_points(cam1_from_ref.double().to(p.device), p)[:, 2]
    return z1.to(particles.position.dtype)


def offset_penalty(offset1: torch.Tensor, offset2: torch.Tensor, depth1: torch.Tensor,
                   depth2: torch.Tensor, alpha1: float, alpha2: float) -> torch.Tensor:
    """``Σ_t α_t / |P| Σ_j ‖δ_t^j‖² / d_t^j``. Shape: offsets (N, 3), depths (N,) -> 0-d."""
    n = offset1.shape[0]
    if n == 0:
        return offset1.sum() * 0
    term1 = (offset1.pow(2).sum(-1) / depth1).sum()
    term2 = (offset2.pow(2).sum(-1) / depth2).sum()
    return (alpha1 * term1 + alpha2 * term2) / n


def attack_loss(flow: torch.Tensor, target: torch.Tensor, particles, depth1: torch.Tensor,
                depth2: torch.Tensor, alpha1: float = DEFAULT_ALPHA,
                alpha2: float = DEFAULT_ALPHA) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The paper's loss. Shape: flow, target (B, 2, H, W) pixels; depths (N,).

    Returns ``(loss, distance, penalty)``: 0-d tensors, ``distance = mean_B AEE(flow, target)``.
    """
    distance = aee(flow, target).mean()
    penalty = offset_penalty(particles.offset1, particles.offset2, depth1, depth2, alpha1, alpha2)
    return distance + penalty, distance, penalty


# -- the loop -----------------------------------------------------------------------------------

def snapshot(particles):
    """A detached CPU copy of a record (of every layer of combined weather)."""
    if isinstance(particles, LayeredParticles):
        return LayeredParticles(tuple(snapshot(r) for r in particles.layers), particles.names)
    atm = particles.atmosphere
    if atm is not None:
        atm = atm.replace(airlight=atm.airlight.detach().cpu().clone(),
                          density=None if atm.density is None
                          else atm.density.detach().cpu().clone(), drift=atm.drift.cpu())
    return particles.replace(**{n: getattr(particles, n).detach().cpu().clone()
                                for n in TENSOR_FIELDS}, atmosphere=atm)


def _matched(pairs: Sequence[FramePair], particles: Sequence) -> tuple[list, list]:
    """The pairs and their records as lists, refusing records not one per pair and pairs of
    different sizes."""
    pairs, records = list(pairs), list(particles)
    if not pairs or len(pairs) != len(records):
        raise ConfigError(f"{len(records)} particle records for {len(pairs)} frame pairs")
    sizes = {tuple(p.image1.shape[-2:]) for p in pairs}
    if len(sizes) != 1:
        raise ConfigError(f"pairs optimised together must have one size; got {sorted(sizes)}")
    return pairs, records


def _device(model: torch.nn.Module, device) -> torch.device:
    """``device``, or by default the model's (the CPU for a model without parameters)."""
    if device is None:
        params = list(model.parameters())
        device = params[0].device if params else torch.device("cpu")
    return torch.device(device)


def _placed(pairs: list, records: list, settings: AttackSettings, device: torch.device
            ) -> tuple[list, list, dict]:
    """``(records, transforms, frames)``: the records on ``device`` as ``settings.compat``
    draws them, each pair's ``(cam1_from_ref, cam2_from_ref)`` and the pairs' frames stacked;
    refuses a record that lives in another frame than its pair's."""
    frames: dict[str, list] = {k: [] for k in ("image1", "image2", "depth1", "depth2",
                                               "intrinsics", "cam1_from_ref", "cam2_from_ref")}
    moved, transforms = [], []
    for pair, record in zip(pairs, records):
        check_pair_for_engine(pair)
        pair = pair.to(device)
        frame, c1, c2 = reference_transforms(pair)
        if record.frame != frame:
            raise ConfigError(f"particles live in {record.frame} coordinates but the frame "
                              f"pair offers {frame} coordinates (sample them for this pair)")
        # (under compat reference, α-blended motion blur is blended sample by sample)
        moved.append(record.for_compat(settings.compat).to(device=device, dtype=torch.float32))
        transforms.append((c1, c2))
        for name in ("image1", "image2", "depth1", "depth2", "intrinsics"):
            frames[name].append(getattr(pair, name))
        frames["cam1_from_ref"].append(c1)
        frames["cam2_from_ref"].append(c2)
    return moved, transforms, {k: torch.stack(v) for k, v in frames.items()}


def _shared_templates(moved: list, settings: AttackSettings):
    """The templates the pairs' records share (None for combined weather, whose layers are each
    drawn with their own); refuses pairs whose weather layers or templates differ."""
    layered = [isinstance(r, LayeredParticles) for r in moved]
    if any(layered):
        if not all(layered) or len({r.names for r in moved}) != 1:
            raise ConfigError("pairs optimised together must have the same weather layers")
        templates = None
    else:
        names = {r.settings.templates for r in moved}
        if len(names) != 1:
            raise ConfigError(f"pairs optimised together must share templates; got "
                              f"{sorted(names)}")
        templates = load_templates(names.pop())
    if settings.layers is not None and not all(layered):
        raise ConfigError("${optimize_layer} applies to combined presets (layers joined by +)")
    return templates


class BatchOptimisation:
    """The attack state of B pairs of one size, optimised together: frames stacked on the device,
    the targets, the rasterised stamps, each pair's own free variables and one Adam optimiser
    over all of them. :func:`attack_batch` runs its steps; the benchmark times exactly the same
    step.

    The loss that is differentiated is the *sum* of the pairs' losses. A pair's variables reach
    only its own frames (the renderer never mixes pairs, the networks in eval mode treat batch
    elements independently), so each pair's gradient is the gradient of its own loss, and Adam,
    being elementwise, moves each pair's variables exactly as an optimiser of its own would: the
    batch gives the results of B single-pair runs up to the order of floating-point reductions.

    Args: as :func:`attack_batch`.
    Attributes: benign (B, 2, H, W) flow on the clean frames and goal (B, 2, H, W) target flow,
    both on the device without gradient; variables, a list of B :class:`WeatherVariables`.
    """

    def __init__(self, model: torch.nn.Module, pairs: Sequence[FramePair], particles: Sequence,
                 settings: AttackSettings, target: TargetSpec = TargetSpec("zero"), *,
                 device=None, target_file_flow: Optional[torch.Tensor] = None):
        pairs, records = _matched(pairs, particles)
        device = _device(model, device)
        moved, transforms, self.frames = _placed(pairs, records, settings, device)
        self.model, self.settings, self.size = model, settings, len(pairs)
        with torch.no_grad():
            self.benign = model(self.frames["image1"], self.frames["image2"])
        self.goal = target_flow(target, self.benign, target_file_flow)
        self.templates = _shared_templates(moved, settings)
        # Scale, rotation, template and defocus are fixed: rasterise the stamps once for all steps.
        self.stamps = (build_stamps(moved, self.templates, device=device)
                       if any(r.count for r in moved) else None)
        self._free(moved, transforms)
        self.detach_occlusion = detaches_occlusion(settings)
        self.optimizer = group_optimizer(self.variables, settings)

    def _free(self, moved: list, transforms: list) -> None:
        """Each pair's free variables for its record in ``moved`` and cameras in ``transforms``,
        and the records and depths its offset penalty weighs."""
        settings = self.settings
        reference = settings.compat == "reference"
        options = dict(transparency_max=settings.transparency_max, homogeneous=reference)
        self.variables = [LayeredVariables(r, settings.optimize, layers=settings.layers,
                                           cam1_from_ref=c1, cam2_from_ref=c2, **options)
                          if isinstance(r, LayeredParticles) else
                          WeatherVariables(r, settings.optimize, cam1_from_ref=c1,
                                           cam2_from_ref=c2, **options)
                          for r, (c1, c2) in zip(moved, transforms)]
        # The penalty weighs the freed particles' offsets (combined weather: the freed layers').
        self.penalised = [sorted(v.freed) if isinstance(v, LayeredVariables) else None
                          for v in self.variables]
        # Per record (frame-1, frame-2) depths, joined into one pair of (N,) tensors.
        self.reg_depths = [tuple(map(torch.cat, zip(*[particle_depths(x, c1, c2)
                                                      for x in self._freed(i, r)])))
                           for i, (r, (c1, c2)) in enumerate(zip(moved, transforms))]
        # The research code's penalty divides by the squared, unclamped frame-1 depth of the
        # starting positions.
        self.start_depth1 = [torch.cat([start_depth(x, c1) for x in self._freed(i, r)])
                             for i, (r, (c1, _)) in enumerate(zip(moved, transforms))]

    def render(self, particles: Sequence):
        """The weather frames of B records (a :class:`~weathergen.engine.RenderOutput`)."""
        return render(**self.frames, particles=list(particles), templates=self.templates,
                      beta=self.settings.beta, stamps=self.stamps,
                      detach_occlusion=self.detach_occlusion)

    def evaluate(self):
        """Render the current variables and run the network.

        Returns ``(records, flow, losses, distances, penalties)``: the B current records, the
        flow (B, 2, H, W) and the (B,) terms of each pair's :func:`attack_loss`, with gradient.
        Sets ``self.depends`` (B bools): whether each pair's loss depends on its own free
        variables (some particle reaches its frames, or the penalty has a freed offset), i.e.
        whether that pair alone would have anything to optimise.
        """
        current = [v.particles() for v in self.variables]
        out = BatchOptimisation.render(self, current)   # B records, also in a PairOptimisation
        flow = self.model(out.image1, out.image2)
        distances = aee(flow, self.goal)
        penalties = [self.penalty(i, r) for i, r in enumerate(current)]
        reached = out.reached.tolist() if out.reached is not None else [True] * self.size
        self.depends = [bool(r) and out.image1.requires_grad or p.requires_grad
                        for r, p in zip(reached, penalties)]
        return current, flow, distances + torch.stack(penalties), distances, torch.stack(penalties)

    def penalty(self, i: int, record) -> torch.Tensor:
        """Pair ``i``'s offset penalty (0-d) for its current ``record``: the paper's
        :func:`offset_penalty` of the record's offsets, or under ``compat="reference"`` the
        research code's (:func:`~weathergen.attack.compat.reference_offset_penalty` of the
        offsets this attack adds)."""
        s = self.settings
        if s.compat == "reference":
            delta = self.variables[i].delta
            return reference_offset_penalty(delta.get("offset1"), delta.get("offset2"),
                                            self.start_depth1[i], s.alpha1, s.alpha2)
        d1, d2 = self.reg_depths[i]
        freed = self._freed(i, record)
        return offset_penalty(torch.cat([r.offset1 for r in freed]),
                              torch.cat([r.offset2 for r in freed]), d1, d2, s.alpha1, s.alpha2)

    def _freed(self, i: int, record) -> list:
        """Pair ``i``'s records whose offsets the penalty weighs: its record, or the freed
        layers of combined weather."""
        if self.penalised[i] is None:
            return [record]
        return [record.layers[k] for k in self.penalised[i]]

    def update(self, loss: torch.Tensor, active: Optional[Sequence[bool]] = None) -> None:
        """One Adam step on the free variables of the ``active`` pairs (default: all), with
        ``loss`` the sum of the pairs' losses. The gradients are cleared first, except under
        ``compat="reference"``, where they add up over the steps as in the research code."""
        if resets_gradients(self.settings):
            self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if active is not None:
            for v, keep in zip(self.variables, active):
                if not keep:
                    for p in v.parameters() + v.atmosphere_parameters():
                        p.grad = None            # a finished pair keeps its variables
        self.optimizer.step()


class PairOptimisation(BatchOptimisation):
    """:class:`BatchOptimisation` of a single pair (B = 1), with single-pair accessors:
    ``variables`` is the pair's :class:`WeatherVariables`, :meth:`render` takes one record and
    :meth:`evaluate` returns ``(particles, flow, loss, distance, penalty)`` with 0-d terms.
    """

    def __init__(self, model: torch.nn.Module, pair: FramePair, particles,
                 settings: AttackSettings, target: TargetSpec = TargetSpec("zero"), *,
                 device=None, target_file_flow: Optional[torch.Tensor] = None):
        super().__init__(model, [pair], [particles], settings, target, device=device,
                         target_file_flow=target_file_flow)
        self.variables = self.variables[0]

    def render(self, particles):
        return super().render([particles])

    def evaluate(self):
        self.variables, single = [self.variables], self.variables
        try:
            current, flow, losses, distances, penalties = super().evaluate()
        finally:
            self.variables = single
        return current[0], flow, losses[0], distances[0], penalties[0]

    def update(self, loss: torch.Tensor) -> None:
        self.variables, single = [self.variables], self.variables
        try:
            super().update(loss)
        finally:
            self.variables = single


def attack_batch(model: torch.nn.Module, pairs: Sequence[FramePair], particles: Sequence,
                 settings: AttackSettings, target: TargetSpec = TargetSpec("zero"), *,
                 device=None, target_file_flow: Optional[torch.Tensor] = None,
                 on_step: Callable[[int, StepRecord], None] = lambda i, r: None
                 ) -> list[AttackResult]:
    """Optimise the records ``particles[i]`` in ``pairs[i]`` against ``model``, all pairs in one
    forward and backward pass per step (see :class:`BatchOptimisation`).

    Args:
        model: a flow network with the package contract, (B, 3, H, W) x2 -> (B, 2, H, W), in
            eval mode; its parameters are not changed.
        pairs: B frame pairs of one size (clean frames, depth, cameras).
        particles: B starting records, one per pair (e.g. from ``sample_particles``).
        settings: :class:`AttackSettings`, shared by the pairs.
        target: :class:`TargetSpec`; for ``"file"`` pass the file's flow as ``target_file_flow``
            (2, H, W).
        device: where rendering and the network run (default: the model's device).
        on_step: called with the pair's index and every :class:`StepRecord` of that pair.
    Returns: one :class:`AttackResult` per pair, each as :func:`attack_pair` gives it for that
    pair alone (best step, history, freeze when nothing of the pair is visible, the end of a
    pair whose loss has converged under ``settings.early_stop``); a record's ``seconds`` is the
    time of the batched step.
    """
    run = BatchOptimisation(model, pairs, particles, settings, target, device=device,
                            target_file_flow=target_file_flow)
    size = run.size
    log = StepLog(size, on_step)
    best_particles: list = [None] * size
    initial_flow: list = [None] * size
    frozen, active = [False] * size, [True] * size
    steps = int(settings.steps)
    for step in range(steps + 1):
        t0 = time.perf_counter()
        current, flow, losses, distances, penalties = run.evaluate()
        dists = distances.detach().cpu().tolist()
        for i in (i for i in range(size) if active[i]):
            if step == 0:
                initial_flow[i] = flow[i:i + 1].detach().cpu()
            if log.improves(i, step, dists[i], flow):
                best_particles[i] = snapshot(current[i])
        last = step == steps
        finishing = [False] * size if last else _finishing(run, log, active, losses)
        going = [a and not f for a, f in zip(active, finishing)]
        if not last and any(going):
            run.update(losses.sum(), going)
        log.record(step, [i for i in range(size) if active[i]], flow, run.benign, losses, dists,
                   penalties, t0)
        for i in range(size):
            if finishing[i]:        # only an active pair can be finishing
                frozen[i], active[i] = not run.depends[i], False
            if last:
                active[i] = False
        del flow, losses, distances, penalties, current
        if not any(active):
            break
    benign, goal = run.benign.cpu(), run.goal.cpu()
    return [AttackResult(best_particles=best_particles[i], best_step=log.best_step[i],
                         history=log.history[i], benign_flow=benign[i:i + 1],
                         initial_flow=initial_flow[i], best_flow=log.best_flow[i],
                         target=goal[i:i + 1], frozen=frozen[i]) for i in range(size)]


def _finishing(run: BatchOptimisation, log: StepLog, active: list, losses: torch.Tensor
               ) -> list[bool]:
    """Which active pairs stop at this step of ``losses``: one none of whose particles reaches
    its frames, and whose penalty depends on no freed variable, has nothing to optimise (it is
    frozen); so does one whose loss has converged (``settings.early_stop``)."""
    stop = run.settings.early_stop
    return [a and (not d or stop is not None and stop.stalled([r.loss for r in log.history[i]]
                                                              + [float(losses[i].detach())]))
            for i, (a, d) in enumerate(zip(active, run.depends))]


def attack_pair(model: torch.nn.Module, pair: FramePair, particles, settings: AttackSettings,
                target: TargetSpec = TargetSpec("zero"), *, device=None,
                target_file_flow: Optional[torch.Tensor] = None,
                on_step: Callable[[StepRecord], None] = lambda r: None) -> AttackResult:
    """Optimise ``particles`` in ``pair`` against ``model``: :func:`attack_batch` of one pair.

    Args:
        model: a flow network with the package contract, (1, 3, H, W) x2 -> (1, 2, H, W); its
            parameters are not changed.
        pair: the frame pair (clean frames, depth, cameras).
        particles: the starting record for this pair (e.g. from ``sample_particles``).
        settings: :class:`AttackSettings`.
        target: :class:`TargetSpec`; for ``"file"`` pass the file's flow as ``target_file_flow``
            (2, H, W).
        device: where rendering and the network run (default: the model's device).
        on_step: called with every :class:`StepRecord` (for progress reports).
    Returns: :class:`AttackResult`.
    """
    return attack_batch(model, [pair], [particles], settings, target, device=device,
                        target_file_flow=target_file_flow,
                        on_step=lambda i, record: on_step(record))[0]
