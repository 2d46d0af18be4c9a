"""How one pair is attacked: the free variables, the number of steps, the learning rate, the
penalty weights and the occlusion sharpness (:class:`AttackSettings`), with the paper's defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

from ..errors import ConfigError

#: The particle variables an attack may optimise, in their canonical order.
OPTIMIZABLE = ("offset1", "offset2", "color", "transparency")
#: The atmosphere's variables (weather fields with a visibility, rain or snow rate): the density
#: lattice, each value between ``1 / DENSITY_FACTOR`` and ``DENSITY_FACTOR`` times its sampled
#: value (optimised in log space: ``ρ = ρ₀ exp(b tanh(Δ / b))``, ``b = ln DENSITY_FACTOR``), and
#: the airlight, each channel in (0, 1).
ATMOSPHERE_VARIABLES = ("density", "airlight")
#: Every variable, in canonical order (``--optimize all``).
VARIABLES = OPTIMIZABLE + ATMOSPHERE_VARIABLES
POSITION_VARIABLES = ("offset1", "offset2")
#: Paper defaults (Section 4.2 and the supplement's attack-configuration table).
DEFAULT_STEPS = 750
DEFAULT_ALPHA = 1000.0
LR_POSITIONS = 1e-5
LR_APPEARANCE = 1e-3
DENSITY_FACTOR = 4.0
#: The learning-rate groups: each freed variable moves at its group's rate (Adam, one parameter
#: group each); the research code's homogeneous component of δ1 moves with the positions.
LR_GROUPS = {"positions": ("offset1", "offset2", "offset1_w"), "color": ("color",),
             "transparency": ("transparency",), "density": ("density",),
             "airlight": ("airlight",)}
#: Default rates of weather fields (particles in metres, colour and transparency in the atanh
#: domain, density in log space, airlight in the atanh domain), measured on the demo scene
#: (docs/attack.md, "Learning rates"). The paper's presets keep the paper's rates
#: (:func:`default_lr`) for their particles; the atmosphere's rates are these for every preset.
FIELD_LR = {"positions": 1e-3, "color": 5e-2, "transparency": 5e-2, "density": 0.3,
            "airlight": 1.0}
#: ``paper``: the paper's equations and tables; ``reference``: the research code's behaviour
#: where it departs from them (see :mod:`weathergen.attack.compat`).
COMPAT_MODES = ("paper", "reference")
#: Where the default rates come from: the paper's table, or :data:`FIELD_LR` (every layer of the
#: preset a weather field).
LR_DEFAULTS = ("paper", "field")


def lr_group(variable: str) -> str:
    """The learning-rate group of a freed variable (:data:`LR_GROUPS`)."""
    return next(g for g, members in LR_GROUPS.items() if variable in members)


def parse_group_lr(items) -> tuple[tuple[str, float], ...]:
    """``["density=0.1", "positions=1e-3"]`` (or ``"density=0.1,color=0.05"``) -> the rates by
    group, in :data:`LR_GROUPS` order. Raises ConfigError naming a bad entry."""
    if isinstance(items, str):
        items = items.split(",")
    out = {}
    for item in items:
        group, sep, value = str(item).partition("=")
        group = group.strip()
        if not sep or group not in LR_GROUPS:
            raise ConfigError(f"${{group_lr}} {item!r}: expected GROUP=RATE with GROUP one of "
                              f"{', '.join(LR_GROUPS)}")
        try:
            rate = float(value)
        except ValueError:
            rate = math.nan
        if not (rate > 0 and math.isfinite(rate)):
            raise ConfigError(f"${{group_lr}} {item!r}: the rate must be a positive number")
        out[group] = rate
    return tuple((g, out[g]) for g in LR_GROUPS if g in out)


def parse_optimize(text: str) -> tuple[str, ...]:
    """``"offset1,color"`` -> ``("offset1", "color")`` in canonical order; ``"all"`` -> every
    variable (:data:`VARIABLES`).

    Raises ConfigError naming the unknown entries and listing the valid ones.
    """
    names = [t.strip() for t in str(text).split(",") if t.strip()]
    if names == ["all"]:
        return VARIABLES
    unknown = [n for n in names if n not in VARIABLES]
    if unknown:
        raise ConfigError(f"${{optimize}}: unknown variable(s) {', '.join(map(repr, unknown))}; "
                          f"choose from {', '.join(VARIABLES)} (comma-separated) or 'all'")
    if not names:
        raise ConfigError(f"${{optimize}}: name at least one of {', '.join(VARIABLES)}")
    return tuple(n for n in VARIABLES if n in names)


def default_optimize(preset) -> tuple[str, ...]:
    """The variables an attack frees when none are named: the particles' four, and the
    atmosphere's density and airlight where the preset (a layer of it) has an atmosphere."""
    layers = getattr(preset, "layers", None) or (preset,)
    if any(getattr(layer, "has_atmosphere", False) for layer in layers):
        return VARIABLES
    return OPTIMIZABLE


def default_lr(optimize: tuple[str, ...]) -> float:
    """1e-5 when positions move (their scale is scene units), 1e-3 for colour/transparency only."""
    return LR_POSITIONS if any(v in POSITION_VARIABLES for v in optimize) else LR_APPEARANCE


def transparency_bound(preset) -> float:
    """The largest transparency θ the attack may reach for particles of ``preset``.

    The paper maps θ to the unbounded domain by ``η = atanh(2θ − 1)`` (Section 3.2), so θ stays
    in (0, 1); a preset whose own θ (the "θ" column of the supplement's particle table: the
    ceiling of its depth hat, or the constant value) exceeds 1, as sparks' 1.5 does, keeps its
    own ceiling. So the bound is ``max(1, θ_preset)``: 1 for snow, rain, fog and grey, 1.5 for
    sparks, whatever the sampled particles happen to reach.
    """
    return max(1.0, float(preset.transparency))


@dataclass(frozen=True)
class EarlyStop:
    """Convergence of one pair's attack: it ends at step ``k`` when the lowest loss of its last
    ``window`` steps (``k - window + 1 ... k``) is not below the lowest loss before them by more
    than ``tol`` times that earlier loss (a relative tolerance). The best iterate is kept as
    always; an attack without it runs every step (the paper's setting).
    """

    window: int
    tol: float

    def __post_init__(self):
        if isinstance(self.window, bool) or not isinstance(self.window, int) or self.window < 1:
            raise ConfigError(f"${{early_stop}}: the window must be a whole number of steps >= 1, "
                              f"got {self.window!r}")
        if not (self.tol >= 0 and math.isfinite(self.tol)):
            raise ConfigError(f"${{early_stop}}: the tolerance must be a finite number >= 0, "
                              f"got {self.tol!r}")

    @classmethod
    def parse(cls, text: str) -> "EarlyStop":
        """``"WINDOW:TOL"`` (``"50:0.001"``) -> EarlyStop; ConfigError for another form."""
        window, sep, tol = str(text).partition(":")
        try:
            numbers = (int(window), float(tol)) if sep else None
        except ValueError:
            numbers = None
        if numbers is None:
            raise ConfigError(f"${{early_stop}} must be WINDOW:TOL (steps and a relative loss "
                              f"tolerance, e.g. 50:0.001), got {text!r}")
        return cls(*numbers)

    def stalled(self, losses: Sequence[float]) -> bool:
        """Whether an attack whose steps ``0 ... k`` had ``losses`` has converged at step ``k``."""
        if len(losses) <= self.window:
            return False
        before = min(losses[:-self.window])
        return min(losses[-self.window:]) >= before - self.tol * abs(before)

    def __str__(self) -> str:
        return f"{self.window}:{self.tol:g}"


@dataclass(frozen=True)
class AttackSettings:
    """How one pair is attacked.

    optimize: the freed variables; steps: Adam updates (``steps + 1`` evaluations: step 0 is the
    unoptimised weather); lr: one rate for every group (``None``: each group's default);
    group_lr: ``((group, rate), ...)``, rates of single groups (:data:`LR_GROUPS`) that win over
    ``lr``; lr_defaults: ``paper`` (the particles at :func:`default_lr`) or ``field``
    (:data:`FIELD_LR`), the defaults of the groups no rate is given for (the atmosphere's are
    :data:`FIELD_LR`'s in both; :attr:`learning_rates` gives the rates used); alpha1/alpha2:
    penalty weights; beta: occlusion sharpness of the renderer during the attack
    (``BETA_ATTACK`` = 30 to differentiate through occlusion, ``BETA_RENDER`` = 250 otherwise);
    transparency_max: the largest θ the attack may reach (:func:`transparency_bound` of the
    preset; ``None``: 1, or the record's largest θ where that is more); compat: ``paper``
    (default) or ``reference``, the research code's terms (:mod:`weathergen.attack.compat`);
    layers: combined weather's layers whose variables are freed, by name (``None``: every layer;
    the others stay as sampled); early_stop: :class:`EarlyStop` to end a pair's attack once its
    loss has converged (``None``: every step, the paper's setting and the only one under
    ``compat="reference"``).
    """

    optimize: tuple[str, ...] = OPTIMIZABLE
    steps: int = DEFAULT_STEPS
    lr: Optional[float] = None
    alpha1: float = DEFAULT_ALPHA
    alpha2: float = DEFAULT_ALPHA
    beta: float = 250.0
    transparency_max: Optional[float] = None
    compat: str = "paper"
    layers: Optional[tuple[str, ...]] = None
    group_lr: tuple[tuple[str, float], ...] = ()
    lr_defaults: str = "paper"
    early_stop: Optional[EarlyStop] = None

    def __post_init__(self):
        parse_optimize(",".join(self.optimize))  # validates names and non-emptiness
        if int(self.steps) < 0:
            raise ConfigError(f"${{steps}} must be >= 0, got {self.steps}")
        if self.lr is not None and not (self.lr > 0 and math.isfinite(self.lr)):
            raise ConfigError(f"${{lr}} must be a positive number, got {self.lr}")
        parse_group_lr([f"{g}={r}" for g, r in self.group_lr])
        if self.lr_defaults not in LR_DEFAULTS:
            raise ConfigError(f"lr_defaults must be one of {', '.join(LR_DEFAULTS)}, "
                              f"got {self.lr_defaults!r}")
        for name in ("alpha1", "alpha2"):
            v = getattr(self, name)
            if not (v >= 0 and math.isfinite(v)):
                raise ConfigError(f"${{{name}}} must be a finite number >= 0, got {v}")
        if not (self.beta > 0 and math.isfinite(self.beta)):
            raise ConfigError(f"occlusion beta must be positive, got {self.beta}")
        if self.transparency_max is not None and not (self.transparency_max > 0
                                                      and math.isfinite(self.transparency_max)):
            raise ConfigError(f"${{transparency_max}} must be a positive number, "
                              f"got {self.transparency_max}")
        if self.layers is not None and not self.layers:
            raise ConfigError("${optimize_layer}: name at least one layer, or 'all'")
        if self.compat not in COMPAT_MODES:
            raise ConfigError(f"${{compat}} must be one of {', '.join(COMPAT_MODES)}, "
                              f"got {self.compat!r}")
        if self.early_stop is not None and self.compat == "reference":
            raise ConfigError("${early_stop} does not apply under ${compat} reference: the "
                              "research code runs every step")

    def group_rate(self, group: str) -> float:
        """Adam's rate of one group (:data:`LR_GROUPS`): its own where given, else ``lr``, else
        the default of :attr:`lr_defaults`."""
        given = dict(self.group_lr)
        if group in given:
            return given[group]
        if self.lr is not None:
            return self.lr
        if self.lr_defaults == "paper" and group in ("positions", "color", "transparency"):
            return default_lr(self.optimize)
        return FIELD_LR[group]

    @property
    def learning_rates(self) -> dict[str, float]:
        """The rate of each freed variable's group, as the optimiser uses it."""
        groups = [g for g in LR_GROUPS if any(lr_group(v) == g for v in self.optimize)]
        return {g: self.group_rate(g) for g in groups}

    def to_dict(self) -> dict:
        return {"optimize": list(self.optimize), "steps": int(self.steps),
                "learning_rates": self.learning_rates, "alpha1": self.alpha1,
                "alpha2": self.alpha2, "beta": self.beta,
                "transparency_max": self.transparency_max, "compat": self.compat,
                **({"layers": list(self.layers)} if self.layers else {}),
                **({"early_stop": str(self.early_stop)} if self.early_stop else {})}
