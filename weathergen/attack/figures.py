"""Figures by region and KITTI's outlier rates of one weather flow, and their means over pairs;
an attacked pair's figures (:class:`PairSummary`).

For a pair with clean-frame flow ``f``, weather-frame flow ``f̌``, the weather's opacity in both
frames and (where the dataset has it) ground truth ``gt``:

- ``aee_weather_px`` / ``aee_clear_px``: AEE(f, f̌) over the pixels the weather covers (opacity
  above :data:`~weathergen.flow.WEATHER_OPACITY_THRESHOLD` in frame 1 or 2) / over the rest;
- ``epe_weather_px`` / ``epe_clear_px``: EPE(f̌, gt) over the same regions (valid pixels only);
- ``fl_all``: KITTI's Fl-all of f̌ (percent of valid pixels with an error above 3 px and 5 % of
  the ground truth's length); ``outliers_1px``, ``outliers_3px``, ``outliers_5px``: percent of
  valid pixels with an error above 1, 3, 5 px;
- ``weather_coverage``: the percentage of pixels the weather covers;
- ``robust_epe``, ``robust_fl``, ``robust_1px``: RobustSpring's robustness figures (Schmalfuss
  et al., 2025), f̌ against f rather than against ground truth: the mean end-point error (the
  same number as AEE(f, f̌)), the percentage of pixels whose error exceeds 3 px and 5 % of the
  clean flow's length (KITTI's Fl rule, with f in place of ground truth) and the percentage whose
  error exceeds 1 px; every pixel counts, no ground truth is needed.

A figure over an empty region, or needing ground truth that the pair lacks, is None. Means over
pairs: region figures are means over the pairs that have them; outlier rates pool the valid
pixels of all pairs (``gt_valid_px`` per pair), as KITTI's evaluation counts them.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Mapping, Optional, Sequence

import torch

from ..engine import render_pair
from ..flow import aee, fl_all, outlier_rate
from ..io.images import to_uint8
from .compat import reference_figure_flows
from .steps import AttackResult

_PER_PAIR, _POOLED = {"mean": "pairs"}, {"mean": "pooled"}


@dataclass(kw_only=True)
class RegionFigures:
    """The figures by region and outlier rates of one pair (see the module doc), declared once for
    every per-pair record that carries them (an evaluation's rows, an attack's pair summaries).
    ``mean`` in a field's metadata says how means over pairs take it: over the pairs that have it
    (``"pairs"``) or pooled over their valid pixels (``"pooled"``)."""

    aee_weather_px: Optional[float] = field(default=None, metadata=_PER_PAIR)
    aee_clear_px: Optional[float] = field(default=None, metadata=_PER_PAIR)
    epe_weather_px: Optional[float] = field(default=None, metadata=_PER_PAIR)
    epe_clear_px: Optional[float] = field(default=None, metadata=_PER_PAIR)
    weather_coverage: Optional[float] = field(default=None, metadata=_PER_PAIR)
    fl_all: Optional[float] = field(default=None, metadata=_POOLED)
    outliers_1px: Optional[float] = field(default=None, metadata=_POOLED)
    outliers_3px: Optional[float] = field(default=None, metadata=_POOLED)
    outliers_5px: Optional[float] = field(default=None, metadata=_POOLED)
    robust_epe: Optional[float] = field(default=None, metadata=_PER_PAIR)
    robust_fl: Optional[float] = field(default=None, metadata=_PER_PAIR)
    robust_1px: Optional[float] = field(default=None, metadata=_PER_PAIR)
    #: the valid ground-truth pixels the outlier rates count (None without ground truth)
    gt_valid_px: Optional[int] = None


#: Per-pair figures averaged over pairs.
REGION_KEYS = tuple(f.name for f in fields(RegionFigures) if f.metadata.get("mean") == "pairs")
#: Per-pair outlier rates, pooled over the pairs' valid pixels.
OUTLIER_KEYS = tuple(f.name for f in fields(RegionFigures) if f.metadata.get("mean") == "pooled")
FIGURE_KEYS = REGION_KEYS + OUTLIER_KEYS
#: A sequence attack's figures of a pair (:mod:`~weathergen.attack.sequence`): the pair attacked
#: alone, and the second camera with stereo (None, and left out of the means, otherwise).
SEQUENCE_FIGURES = ("per_pair_aee_adversarial", "per_pair_target_adversarial",
                    "second_aee_random", "second_aee_adversarial")


def _masked(flow, target, mask) -> Optional[float]:
    if not bool(mask.any()):
        return None
    return float(aee(flow, target, mask)[0])


def region_figures(clean: torch.Tensor, weather: torch.Tensor,
                   covered: Optional[torch.Tensor] = None, gt: Optional[torch.Tensor] = None,
                   valid: Optional[torch.Tensor] = None) -> dict:
    """The figures of :data:`FIGURE_KEYS` for one pair, plus ``gt_valid_px`` (None without gt).

    Shape: clean, weather (1, 2, H, W) pixels; covered (H, W) bool, the weather's pixels (None:
    no weather, e.g. an Lp perturbation); gt (2, H, W); valid (1, H, W) bool (None: all valid).
    """
    clean, weather = clean.detach().cpu().float(), weather.detach().cpu().float()
    h, w = clean.shape[-2:]
    covered = (torch.zeros(h, w, dtype=torch.bool) if covered is None
               else covered.detach().cpu().reshape(h, w).bool())[None]          # (1, H, W)
    out: dict = {key: None for key in FIGURE_KEYS}
    out["gt_valid_px"] = None
    out["aee_weather_px"] = _masked(weather, clean, covered)
    out["aee_clear_px"] = _masked(weather, clean, ~covered)
    out["weather_coverage"] = 100.0 * float(covered.float().mean())
    out["robust_epe"] = float(aee(weather, clean)[0])
    out["robust_fl"] = float(fl_all(weather, clean)[0])
    out["robust_1px"] = float(outlier_rate(weather, clean, 1.0)[0])
    if gt is None:
        return out
    gt = gt.detach().cpu().float()[None]
    ok = (torch.ones(1, h, w, dtype=torch.bool) if valid is None
          else valid.detach().cpu().reshape(1, h, w).bool())
    out["gt_valid_px"] = int(ok.sum())
    out["epe_weather_px"] = _masked(weather, gt, ok & covered)
    out["epe_clear_px"] = _masked(weather, gt, ok & ~covered)
    if out["gt_valid_px"]:
        out["fl_all"] = float(fl_all(weather, gt, ok)[0])
        for px in (1, 3, 5):
            out[f"outliers_{px}px"] = float(outlier_rate(weather, gt, float(px), ok)[0])
    return out


def mean_figures(rows: Sequence[Mapping]) -> dict:
    """Means over pairs of :data:`FIGURE_KEYS` (see the module doc); None where no pair has one."""
    out: dict = {}
    for key in REGION_KEYS:
        values = [r[key] for r in rows if r.get(key) is not None]
        out[key] = sum(values) / len(values) if values else None
    for key in OUTLIER_KEYS:
        pairs = [(r[key], r["gt_valid_px"]) for r in rows
                 if r.get(key) is not None and r.get("gt_valid_px")]
        total = sum(n for _, n in pairs)
        out[key] = sum(v * n for v, n in pairs) / total if total else None
    return out


def written_flow(model, pair, particles, beta: float, device) -> tuple:
    """A record as an attack writes it: ``(the record at storage precision, its rendering, the
    8-bit frames, the network's flow on them (1, 2, H, W) on the CPU)``, the flow the figures of
    the files on disk describe (``evaluate --weather OUT`` measures the same)."""
    best = particles.quantized()
    with torch.no_grad():
        rendered = render_pair(pair, best, beta=beta, device=device)
    frames = tuple(to_uint8(img[0].permute(1, 2, 0).cpu().numpy())
                   for img in (rendered.image1, rendered.image2))
    stored = [torch.from_numpy(f).permute(2, 0, 1)[None].float().div(255).to(device)
              for f in frames]
    with torch.no_grad():
        return best, rendered, frames, model(*stored).cpu()


@dataclass
class PairSummary(RegionFigures):
    """Per-pair figures of an attack (pixels). ``epe_*`` are None without ground truth.

    aee_random: AEE(f, f̌) for the unoptimised weather (step 0, float frames); aee_adversarial:
    for the best step as written (particles at storage precision, 8-bit frames);
    target_initial / target_adversarial: AEE(f̌, target) for the same two flows. The figures by
    region and the outlier rates (:class:`~weathergen.attack.figures.RegionFigures`) describe the
    adversarial flow.
    """

    pair: str
    best_step: int
    steps: int
    aee_random: float
    aee_adversarial: float
    target_initial: float
    target_adversarial: float
    epe_benign: Optional[float] = None
    epe_random: Optional[float] = None
    epe_adversarial: Optional[float] = None
    seconds: float = 0.0
    nothing_visible: bool = False     # no particle could change the flow: nothing was optimised
    particles: Optional[int] = None   # particles in the record (the count the frame size gave)
    #: ``attack --sequence``: the figures of each pair attacked alone, same settings and start
    per_pair_aee_adversarial: Optional[float] = None
    per_pair_target_adversarial: Optional[float] = None
    #: ``attack --sequence --stereo``: AEE(f, f̌) of the second camera (float frames)
    second_aee_random: Optional[float] = None
    second_aee_adversarial: Optional[float] = None

    @classmethod
    def from_dict(cls, data: dict) -> "PairSummary":
        """A summary stored by :func:`dataclasses.asdict`; unknown keys are ignored."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})


def summarize_pair(pair_name: str, result: AttackResult, adversarial_flow: torch.Tensor,
                   gt_flow: Optional[torch.Tensor] = None,
                   gt_valid: Optional[torch.Tensor] = None, seconds: float = 0.0,
                   compat: str = "paper", covered: Optional[torch.Tensor] = None) -> PairSummary:
    """Figures of one attacked pair. ``adversarial_flow`` is the flow on the frames as written
    (best particles at storage precision, 8-bit frames); ``covered`` (H, W) bool the pixels its
    weather covers (:func:`~weathergen.flow.weather_mask`; None: none, as for an Lp attack), for
    the figures by region, which compare the adversarial flow with the clean one.

    ``compat="reference"`` measures the adversarial figures as the research code does: on the
    best step's float frames (``result.best_flow``), and ``aee_adversarial`` against the random
    weather's flow when a step beat step 0
    (:func:`~weathergen.attack.compat.reference_figure_flows`).
    Shape: flows (1, 2, H, W); gt (2, H, W), valid (1, H, W).
    """
    benign, initial, adv, goal, best = (t.detach().cpu().float() for t in
                                        (result.benign_flow, result.initial_flow,
                                         adversarial_flow, result.target, result.best_flow))
    if compat == "reference":
        adv = best
        measured, against = reference_figure_flows(result.best_step, benign, initial, best)
    else:
        measured, against = adv, benign
    summary = PairSummary(
        pair=pair_name, best_step=result.best_step, steps=len(result.history) - 1,
        aee_random=float(aee(initial, benign).mean()),
        aee_adversarial=float(aee(measured, against).mean()),
        target_initial=float(aee(initial, goal).mean()),
        target_adversarial=float(aee(adv, goal).mean()), seconds=seconds,
        nothing_visible=bool(result.frozen))
    for key, value in region_figures(benign, adv, covered, gt_flow, gt_valid).items():
        setattr(summary, key, value)
    if gt_flow is not None:
        gt = gt_flow.detach().cpu().float()[None]
        valid = None if gt_valid is None else gt_valid.detach().cpu()[None]
        summary.epe_benign = float(aee(benign, gt, valid).mean())
        summary.epe_random = float(aee(initial, gt, valid).mean())
        summary.epe_adversarial = float(aee(adv, gt, valid).mean())
    return summary


def mean_summary(rows: list[PairSummary]) -> dict:
    """Means over pairs of every figure (EPE means over the pairs that have ground truth; the
    figures by region and outlier rates as :func:`~weathergen.attack.figures.mean_figures`)."""
    out: dict = {"pairs": len(rows)}
    for key in ("aee_random", "aee_adversarial", "target_initial", "target_adversarial",
                "epe_benign", "epe_random", "epe_adversarial", *SEQUENCE_FIGURES):
        values = [getattr(r, key) for r in rows if getattr(r, key) is not None]
        if values or key not in SEQUENCE_FIGURES:       # (those only where measured)
            out[key] = sum(values) / len(values) if values else None
    out.update(mean_figures([{k: getattr(r, k) for k in (*FIGURE_KEYS, "gt_valid_px")}
                             for r in rows]))
    return out
