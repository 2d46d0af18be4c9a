"""Flow networks under weather: adversarial attacks and robustness figures.

- :mod:`.settings`: how one pair is attacked (:class:`AttackSettings`, the freed variables);
- :mod:`.configs`: the named attack configurations of the paper's supplement;
- :mod:`.targets`: the flow an attack pushes the network towards;
- :mod:`.plan`: the precedence rules that turn a request into settings;
- :mod:`.compat`: the terms in which the research code departs from the paper
  (``compat="reference"``);
- :mod:`.lp`: the Lp baselines PCFA (L2) and I-FGSM (L∞), perturbing the frames themselves;
- :mod:`.pair`: the optimisation of one pair (tensors in, tensors out, no file I/O);
- :mod:`.job`: the attack over a dataset, writing through :mod:`weathergen.outputs`;
- :mod:`.evaluate`: robustness of a network to the weather of a render or attack output.

Typical use::

    from weathergen.attack import AttackSettings, TargetSpec, attack_pair
    result = attack_pair(model, pair, particles, AttackSettings(steps=20), TargetSpec("zero"))
"""

from __future__ import annotations

from .compat import COMPAT_MODES
from .configs import ATTACK_CONFIGS, AttackConfig, attack_config
from .evaluate import EvalRow, default_evaluation_path, mean_rows, run_evaluation, write_evaluation
from .job import AttackJob, PairReport, attack_refs, job_model, probe_job_network, run_attack
from .lp import (LP_DEFAULTS, LP_METHODS, PCFA_OPTIMIZERS, LpOptimisation, LpResult, LpSettings, l2_normalised,
                 l2_normalised_per_pair, lp_attack_batch, lp_pass_name,
                 lp_settings, plan_lp, random_perturbation)
from .figures import PairSummary, mean_summary, summarize_pair
from .pair import (MIN_REG_DEPTH, AttackResult, BatchOptimisation, PairOptimisation, StepRecord,
                   WeatherVariables, attack_batch, attack_loss, attack_pair, offset_penalty,
                   particle_depths)
from .sequence import (SceneWeather, SecondView, attack_sequence, scene_weather, second_frames,
                       second_view)
from .plan import AttackPlan, attack_pass_name, default_attack_out, plan_attack
from .settings import (ATMOSPHERE_VARIABLES, DEFAULT_ALPHA, DEFAULT_STEPS, DENSITY_FACTOR,
                       FIELD_LR, LR_APPEARANCE, LR_GROUPS, LR_POSITIONS, OPTIMIZABLE,
                       POSITION_VARIABLES, VARIABLES, AttackSettings, EarlyStop, default_lr,
                       default_optimize, parse_group_lr, parse_optimize, transparency_bound)
from .targets import TargetSpec, parse_target, read_target_flow, target_flow

__all__ = ["COMPAT_MODES", "LP_DEFAULTS", "LP_METHODS", "PCFA_OPTIMIZERS", "LpOptimisation", "LpResult",
           "LpSettings", "job_model", "probe_job_network",
           "l2_normalised", "l2_normalised_per_pair", "lp_attack_batch", "lp_pass_name",
           "lp_settings", "plan_lp",
           "random_perturbation", "AttackPlan", "attack_pass_name", "default_attack_out", "plan_attack",
           "ATMOSPHERE_VARIABLES", "ATTACK_CONFIGS", "AttackConfig", "AttackJob", "AttackResult", "AttackSettings",
           "EarlyStop",
           "DEFAULT_ALPHA", "DEFAULT_STEPS", "EvalRow", "LR_APPEARANCE", "LR_GROUPS",
           "LR_POSITIONS", "DENSITY_FACTOR", "FIELD_LR", "parse_group_lr", "VARIABLES", "default_optimize",
           "MIN_REG_DEPTH", "OPTIMIZABLE", "POSITION_VARIABLES", "PairOptimisation", "PairReport",
           "PairSummary", "StepRecord", "TargetSpec", "WeatherVariables", "attack_config",
           "attack_loss", "attack_batch", "attack_pair", "attack_refs", "BatchOptimisation",
           "default_evaluation_path", "default_lr",
           "mean_rows", "mean_summary", "offset_penalty", "parse_optimize", "parse_target",
           "particle_depths", "read_target_flow", "run_attack",
           "run_evaluation", "summarize_pair", "target_flow", "transparency_bound",
           "write_evaluation", "SceneWeather", "attack_sequence", "scene_weather",
           "SecondView", "second_frames", "second_view"]
