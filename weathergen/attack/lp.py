"""The two Lp baselines the weather attack is compared with: PCFA (L2) and I-FGSM (L∞).

Both perturb the two frames of a pair directly (pixels, not particles) and push the network's
flow towards the same target as the weather attack, measuring the same distance
``AEE(f̌, f_target)``; the job runner writes the same files and figures, so the three compare
pair by pair. Tensors in, tensors out, no file I/O.

**PCFA** (Schmalfuss et al., "A Perturbation-Constrained Adversarial Attack for Evaluating the
Robustness of Optical Flow", ECCV 2022). The perturbation ``δ = (δ1, δ2)`` of both frames
("disjoint": one per frame) is bounded jointly in the *normalised* L2 norm::

    ‖δ‖ = ‖δ‖_2 / sqrt(2 · 3 · H · W)  <=  ε_2        (default ε_2 = 5e-3, as the paper used)

i.e. the root mean square over every pixel and channel of both frames. The box ``[0, 1]`` holds
by construction: the frames are ``x = from_atanh(w)`` (change of variables, the paper's "COV"
box constraint) and ``w`` is optimised. Loss, as the reference implementation's:
``AEE(f̌, f_target) + μ · max(0, ‖δ‖² − ε_2²)`` with ``μ = 2500 / ε_2`` for the zero-flow target
and 1.5 times that for any other target. Two optimisers (``optimizer``):

- ``lbfgs`` (the default): as published and as the paper ran it, L-BFGS over both frames'
  variables (PyTorch's, step size ``lr`` = 1, no line search), 20 steps of up to 10 iterations
  (each iteration one network pass with its backward pass). The penalty alone keeps ``δ`` near
  the ball, so a step may lie outside it; only steps within the bound count as the best step.
- ``adam``: Adam (``lr``, default 1e-3 on ``w``, 20 steps: one network pass per step instead of
  up to ten) and, after every step, a ``δ`` outside the ball is scaled back onto it (scaling
  towards the clean frames keeps the box), so *every* step respects the bound.

Either way the written best step is the one closest to the target among the steps within the
bound (step 0, the clean frames, always is).

**I-FGSM** (iterative fast gradient sign method, Kurakin et al.; for optical flow Schrodi et al.,
CVPR 2022; the DistractingDownpour paper's comparison used ``ε_∞ = 5e-3`` and 25 steps)::

    x ← clip_[x0 − ε, x0 + ε] ∩ [0, 1] ( x − α · sign(∇_x AEE(f̌, f_target)) )

on both frames, starting at the clean frames. The reference implementation has only a step
size and a step count and clips to the box; the bound ``ε_∞`` after 25 steps means a step size
of ``ε_∞ / 25``, so the default is ``α = ε / steps`` (the projection onto the ε-ball then never
moves a pixel, and the run is the reference's); a larger ``--lr`` makes the projection bind.

**The "random" column.** A weather attack starts from random weather, so its ``aee_random`` is
the robustness to unoptimised weather. For an Lp attack the comparable figure is a random
perturbation *of the same budget* (drawn per pair from the run seed): uniform signs ``±ε_∞`` for
I-FGSM, a Gaussian direction scaled to ``‖δ‖ = ε_2`` and clipped to the box for PCFA. Its flow is
written as ``initial.flo`` and its figures as ``aee_random`` / ``target_initial``. The
optimisation itself starts at the clean frames (step 0 of the log), as in both papers.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from typing import Callable, Optional, Sequence

import torch

from ..engine import from_atanh, to_atanh
from ..engine.weather.presets import Plausible
from ..errors import ConfigError
from ..flow import aee
from .steps import AttackResult, StepLog, StepRecord
from .targets import TargetSpec, target_flow

LP_METHODS = ("pcfa", "ifgsm")
#: Defaults per method: ε (PCFA: normalised L2; I-FGSM: L∞), steps, lr (PCFA: that of its
#: optimiser, :data:`PCFA_LR`; I-FGSM: None = ε / steps).
LP_DEFAULTS = {"pcfa": {"epsilon": 5e-3, "steps": 20, "lr": None},
               "ifgsm": {"epsilon": 5e-3, "steps": 25, "lr": None}}
#: Where ε plausibly lies: the perturbation is measured on pixel values in [0, 1] (PCFA's
#: normalised L2 is a root mean square over them), so a bound of 1 allows any frames; a bound
#: given on the 0-255 scale (8 for 8/255) is the usual slip.
EPSILON_RANGE = Plausible(0, 1, "", ((1 / 255, "on the 0-255 scale"),),
                          what="perturbations of pixel values in [0, 1]")
#: PCFA's optimisers, the published one (L-BFGS) first: the default.
PCFA_OPTIMIZERS = ("lbfgs", "adam")
#: PCFA's default step size per optimiser: L-BFGS's 1 (PyTorch's, which the reference keeps),
#: Adam's learning rate on the tanh variables.
PCFA_LR = {"lbfgs": 1.0, "adam": 1e-3}
#: L-BFGS iterations per PCFA step (the reference implementation's ``max_iter``).
PCFA_LBFGS_ITERATIONS = 10
#: PCFA's penalty weight is this over ε_2 (zero-flow target), times
#: :data:`PCFA_MU_OTHER_TARGETS` for any other target (the reference implementation's rule).
PCFA_MU_NUMERATOR = 2500.0
PCFA_MU_OTHER_TARGETS = 1.5


@dataclass(frozen=True)
class LpSettings:
    """How one pair is attacked by an Lp baseline.

    method: ``pcfa`` or ``ifgsm``; epsilon: the bound (PCFA: normalised L2 over both frames;
    I-FGSM: L∞ per pixel); steps; lr: PCFA's optimiser's step size (L-BFGS) or learning rate
    (Adam), I-FGSM's step size α; optimizer: PCFA's (``lbfgs`` or ``adam``), None for I-FGSM.
    """

    method: str
    epsilon: float
    steps: int
    lr: float
    optimizer: Optional[str] = None

    def to_dict(self) -> dict:
        out = asdict(self)
        if out["optimizer"] is None:
            del out["optimizer"]
        return {**out, "norm": "L2 (normalised)" if self.method == "pcfa" else "Linf"}


def lp_settings(method: str, epsilon: Optional[float] = None, steps: Optional[int] = None,
                lr: Optional[float] = None, optimizer: Optional[str] = None) -> LpSettings:
    """Settings for ``method`` with its defaults where a value is None (PCFA's optimiser:
    ``lbfgs``); ConfigError on bad values."""
    if method not in LP_METHODS:
        raise ConfigError(f"${{method}} {method!r}: expected weather, {', '.join(LP_METHODS)}")
    if method != "pcfa" and optimizer is not None:
        raise ConfigError(f"${{optimizer}} applies to ${{method}} pcfa only, not to {method}")
    if method == "pcfa":
        optimizer = PCFA_OPTIMIZERS[0] if optimizer is None else optimizer
        if optimizer not in PCFA_OPTIMIZERS:
            raise ConfigError(f"${{optimizer}} {optimizer!r}: expected "
                              f"{' or '.join(PCFA_OPTIMIZERS)}")
    d = LP_DEFAULTS[method]
    eps = float(d["epsilon"] if epsilon is None else epsilon)
    if not (math.isfinite(eps) and eps > 0):
        raise ConfigError(f"${{epsilon}} must be a positive number, not {epsilon!r}")
    problem = EPSILON_RANGE.problem(eps)
    if problem is not None:
        raise ConfigError(f"${{epsilon}} {eps:g}: {problem}")
    n = int(d["steps"] if steps is None else steps)
    if n < 0:
        raise ConfigError("${steps} must be >= 0")
    rate = lr if lr is not None else d["lr"]
    if rate is None:
        rate = PCFA_LR[optimizer] if method == "pcfa" else eps / max(n, 1)
    rate = float(rate)
    if not (math.isfinite(rate) and rate > 0):
        raise ConfigError(f"${{lr}} must be a positive number, not {lr!r}")
    return LpSettings(method, eps, n, rate, optimizer)


def l2_normalised(delta1: torch.Tensor, delta2: torch.Tensor) -> torch.Tensor:
    """PCFA's norm of a perturbation of both frames: ``‖(δ1, δ2)‖_2 / sqrt(numel)``, a 0-d tensor
    (the root mean square over every pixel and channel of both frames)."""
    sq = delta1.pow(2).sum() + delta2.pow(2).sum()
    return (sq / (delta1.numel() + delta2.numel())).sqrt()


def l2_normalised_per_pair(delta1: torch.Tensor, delta2: torch.Tensor) -> torch.Tensor:
    """:func:`l2_normalised` of each pair of a batch: (B, 3, H, W) x2 -> (B,)."""
    sq = delta1.pow(2).flatten(1).sum(1) + delta2.pow(2).flatten(1).sum(1)
    return (sq / (delta1[0].numel() + delta2[0].numel())).sqrt()


def random_perturbation(method: str, x1: torch.Tensor, x2: torch.Tensor, epsilon: float,
                        seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Frames with a random perturbation of the method's budget (the "random" column), in the box.

    Shape: x1, x2 (1, 3, H, W) in [0, 1]; returns the same.
    """
    g = torch.Generator().manual_seed(int(seed) & 0x7FFF_FFFF_FFFF_FFFF)
    if method == "ifgsm":
        d = [(torch.randint(0, 2, x.shape, generator=g).to(x) * 2 - 1) * epsilon for x in (x1, x2)]
    else:
        d = [torch.randn(x.shape, generator=g).to(x) for x in (x1, x2)]
        scale = epsilon / float(l2_normalised(*d))
        d = [t * scale for t in d]
    # clipping to the box moves every pixel towards the clean one: both norms can only shrink
    return (x1 + d[0]).clamp(0, 1), (x2 + d[1]).clamp(0, 1)


class LpOptimisation:
    """The Lp attack state of B pairs of one size, optimised together: clean frames, targets,
    the frames being optimised.

    The loss that is differentiated is the *sum* of the pairs' losses; a network in eval mode
    treats batch elements independently, so each pair's gradient is that of its own loss, and
    both updates (Adam, elementwise; the sign step of I-FGSM) and both projections act per pair:
    a batch gives the results of B single-pair runs up to floating-point rounding. L-BFGS is
    not elementwise (its curvature estimate couples everything it optimises), so
    :func:`lp_attack_batch` gives it one pair at a time.

    Args: model (the package contract), image1/image2 (B, 3, H, W) in [0, 1] on the device,
    :class:`LpSettings`, :class:`TargetSpec`, target_file_flow (2, H, W) for a file target.
    Attributes: benign and goal flows (B, 2, H, W); :meth:`frames` the current frames.
    """

    def __init__(self, model, image1: torch.Tensor, image2: torch.Tensor, settings: LpSettings,
                 target: TargetSpec = TargetSpec("zero"),
                 target_file_flow: Optional[torch.Tensor] = None):
        if image1.dim() != 4 or image1.shape != image2.shape:
            raise ConfigError(f"frames of an Lp attack must be (B, 3, H, W) of one size; got "
                              f"{tuple(image1.shape)} and {tuple(image2.shape)}")
        self.model, self.settings, self.size = model, settings, int(image1.shape[0])
        self.x0 = (image1.detach().float(), image2.detach().float())
        with torch.no_grad():
            self.benign = model(*self.x0)
        self.goal = target_flow(target, self.benign, target_file_flow)
        if settings.method == "pcfa":
            self.w = [to_atanh(x).requires_grad_(True) for x in self.x0]
            if settings.optimizer == "adam":
                self.optimizer = torch.optim.Adam(self.w, lr=settings.lr)
            else:
                self.optimizer = torch.optim.LBFGS(self.w, lr=settings.lr,
                                                   max_iter=PCFA_LBFGS_ITERATIONS)
            # PCFA's penalty weight μ for the bound and the target.
            self.mu = PCFA_MU_NUMERATOR / settings.epsilon * (
                1.0 if target.kind == "zero" else PCFA_MU_OTHER_TARGETS)
        else:
            self.x = [x.clone().requires_grad_(True) for x in self.x0]

    def frames(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The current perturbed frames (with gradient to the optimised variables)."""
        if self.settings.method == "pcfa":
            return from_atanh(self.w[0]), from_atanh(self.w[1])
        return self.x[0], self.x[1]

    def evaluate(self):
        """``(frames, flow, losses, distances, penalties)`` for the current frames, with
        gradient; the last three are (B,): each pair's loss, ``AEE(f̌, f_target)`` and bound
        penalty (0 for I-FGSM)."""
        x1, x2 = self.frames()
        flow = self.model(x1, x2)
        distances = aee(flow, self.goal)
        if self.settings.method == "pcfa":
            norms = l2_normalised_per_pair(x1 - self.x0[0], x2 - self.x0[1])
            penalties = self.mu * torch.relu(norms.pow(2) - self.settings.epsilon ** 2)
        else:
            penalties = torch.zeros_like(distances)
        return (x1, x2), flow, distances + penalties, distances, penalties

    def update(self, loss: torch.Tensor) -> None:
        """One step on ``loss`` (the pairs' losses at the current frames, summed here), then the
        projection onto the constraint set (Adam, I-FGSM). An L-BFGS step re-evaluates the loss
        at each of its iterations, the first at the current frames: ``loss`` itself."""
        loss = loss.sum()
        if self.settings.method == "pcfa" and self.settings.optimizer == "lbfgs":
            first = [loss]

            def closure():
                self.optimizer.zero_grad(set_to_none=True)
                value = first.pop() if first else self.evaluate()[2].sum()
                value.backward()
                return value

            self.optimizer.step(closure)
        elif self.settings.method == "pcfa":
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            self._project_l2()
        else:
            grads = torch.autograd.grad(loss, self.x)
            eps, alpha = self.settings.epsilon, self.settings.lr
            with torch.no_grad():
                for x, x0, g in zip(self.x, self.x0, grads):
                    x -= alpha * g.sign()
                    x.copy_(torch.minimum(torch.maximum(x, x0 - eps), x0 + eps).clamp_(0, 1))

    @torch.no_grad()
    def _project_l2(self) -> None:
        """Scale each pair's perturbation outside the ball back onto it (towards the clean
        frames, which keeps the box)."""
        eps = self.settings.epsilon
        for _ in range(8):   # the tanh round trip can land a hair outside: shrink again
            x1, x2 = self.frames()
            d1, d2 = x1 - self.x0[0], x2 - self.x0[1]
            norms = l2_normalised_per_pair(d1, d2)
            outside = norms > eps
            if not bool(outside.any()):
                return
            scale = torch.where(outside, eps / norms.clamp_min(1e-30) * (1 - 1e-4),
                                torch.ones_like(norms)).view(-1, 1, 1, 1)
            for w, x0, d in zip(self.w, self.x0, (d1, d2)):
                moved = to_atanh(x0 + scale * d)
                # pairs inside the ball keep their variables bit for bit
                w.copy_(torch.where(outside.view(-1, 1, 1, 1), moved, w))
        raise RuntimeError("PCFA projection did not reach the L2 ball")   # not reachable in practice


@dataclass
class LpResult(AttackResult):
    """:class:`AttackResult` of an Lp attack; ``best_frames`` the two best frames (1, 3, H, W)
    on the CPU, ``random_frames`` the random-perturbation frames; ``best_particles`` is None."""

    best_frames: tuple = ()
    random_frames: tuple = ()


def lp_attack_batch(model, images1: torch.Tensor, images2: torch.Tensor, settings: LpSettings,
                    target: TargetSpec = TargetSpec("zero"), *, seeds: Sequence[int],
                    target_file_flow: Optional[torch.Tensor] = None,
                    on_step: Callable[[int, StepRecord], None] = lambda i, r: None
                    ) -> list[LpResult]:
    """Attack B pairs' frames with ``settings.method``, in one forward and backward pass per
    step (see :class:`LpOptimisation`); keep each pair's step closest to its target.

    Shape: images1, images2 (B, 3, H, W) in [0, 1] on the model's device; ``seeds`` (B) draw
    each pair's random-perturbation frames. Every step (0 = clean frames) is measured like the
    weather attack's (``penalty`` is PCFA's bound penalty, 0 for I-FGSM); ``on_step`` gets the
    pair's index and its record. Only steps within the bound (zero penalty) can be the best.
    Returns one :class:`LpResult` per pair, as a batch of that pair alone gives it (up to
    floating-point rounding; PCFA with L-BFGS runs the pairs one after the other).
    """
    if len(seeds) != images1.shape[0]:
        raise ConfigError(f"{len(seeds)} seeds for {images1.shape[0]} frame pairs")
    if settings.optimizer == "lbfgs" and images1.shape[0] > 1:
        results = []
        for i, seed in enumerate(seeds):
            results += lp_attack_batch(model, images1[i:i + 1], images2[i:i + 1], settings,
                                       target, seeds=[seed], target_file_flow=target_file_flow,
                                       on_step=lambda _, record, i=i: on_step(i, record))
        return results
    run = LpOptimisation(model, images1, images2, settings, target, target_file_flow)
    size = run.size
    rand = [random_perturbation(settings.method, run.x0[0][i:i + 1], run.x0[1][i:i + 1],
                                settings.epsilon, seed) for i, seed in enumerate(seeds)]
    rand1, rand2 = torch.cat([r[0] for r in rand]), torch.cat([r[1] for r in rand])
    with torch.no_grad():
        random_flow = model(rand1, rand2).cpu()
    log = StepLog(size, on_step)
    best_frames: list = [None] * size
    steps = int(settings.steps)
    for step in range(steps + 1):
        t0 = time.perf_counter()
        frames, flow, losses, distances, penalties = run.evaluate()
        dists = distances.detach().cpu().tolist()
        within = (penalties <= 0).tolist()
        for i in range(size):
            if within[i] and log.improves(i, step, dists[i], flow):
                best_frames[i] = tuple(f[i:i + 1].detach().cpu().clone() for f in frames)
        if step < steps:
            run.update(losses)
        log.record(step, range(size), flow, run.benign, losses, dists, penalties, t0)
        del flow, losses, distances, penalties, frames
    benign, goal = run.benign.cpu(), run.goal.cpu()
    return [LpResult(best_particles=None, best_step=log.best_step[i], history=log.history[i],
                     benign_flow=benign[i:i + 1], initial_flow=random_flow[i:i + 1],
                     best_flow=log.best_flow[i], target=goal[i:i + 1], best_frames=best_frames[i],
                     random_frames=(rand1[i:i + 1].cpu(), rand2[i:i + 1].cpu()))
            for i in range(size)]


def plan_lp(method: str, epsilon: Optional[float] = None, steps: Optional[int] = None,
            lr: Optional[float] = None, optimizer: Optional[str] = None,
            **weather_options) -> LpSettings:
    """The settings of an Lp attack request; a weather option given with it (any of
    ``weather_options`` not None, e.g. ``preset``, ``optimize``) is refused: an Lp attack has no
    particles."""
    given = [name for name, value in weather_options.items() if value not in (None, (), [], False)]
    if given:
        raise ConfigError(f"${{{given[0]}}} applies to weather attacks only, not to "
                          f"${{method}} {method}")
    return lp_settings(method, epsilon, steps, lr, optimizer)


def lp_pass_name(method: str, input_pass: str) -> str:
    """The output pass of an Lp attack: ``<method>_<input pass>``, e.g. ``pcfa_clean``."""
    return f"{method}_{input_pass}"
