"""Severity ladders: a weather's light, moderate and heavy presets as one curve per network, and
the robustness score made from it.

A ladder is a weather with a bundled preset for each rung, ``<weather>-light``,
``<weather>-moderate``, ``<weather>-heavy`` (snow, rain, sparks, fog). ``benchmark --ladder
snow`` adds those presets to the grid, one attack run per network and rung, so that each rung
has the random weather (the run's step 0) and the adversarial weather (its best step).

Per network, ladder and mode (random, adversarial) the curve holds, rung by rung after the clean
frames (rung 0):

- ``aee``: AEE(f, f̌), the mean distance between the flow on the clean and on the weather
  frames (0 on the clean frames), needing no ground truth;
- ``epe``: the end-point error of the flow against the ground truth (``epe_benign`` on the clean
  frames, ``epe_random`` / ``epe_adversarial`` under weather), where the dataset has it.

Two scores come from a curve (docs/attack.md, "Severity ladders", gives the definitions and their
sources):

- the **robustness score** ``R = (1/S) Σ_s AEE_s(f, f̌)`` over the S rungs: how far the weather
  moves the network's own prediction, whatever its accuracy (a network that answers the same
  flow with and without weather scores 0, however wrong that flow is);
- the **relative corruption error** ``RCE = (1/S) Σ_s (EPE_s − EPE_clean)``: how much the error
  against the ground truth grows, relative to the network's own clean error (Hendrycks and
  Dietterich's relative corruption error, here unnormalised, per rung in pixels).

A score is None until every rung of its curve has finished (a partial mean would not compare).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence

from ..engine import list_presets
from ..errors import ConfigError

#: The rungs of a ladder, lightest first: preset ``<weather>-<rung>``.
RUNGS = ("light", "moderate", "heavy")
#: The two kinds of weather every rung is measured with, and the summary keys they read.
MODES = {"random": ("aee_random", "epe_random"), "adversarial": ("aee_adversarial", "epe_adversarial")}


def available_ladders() -> list[str]:
    """The weathers with a bundled preset for every rung, sorted."""
    presets = set(list_presets())
    weathers = {name.rsplit("-", 1)[0] for name in presets if name.endswith("-" + RUNGS[0])}
    return sorted(w for w in weathers if all(f"{w}-{rung}" in presets for rung in RUNGS))


def ladder_presets(ladder: str) -> list[str]:
    """The presets of ``ladder``, lightest first (``snow`` -> snow-light, snow-moderate,
    snow-heavy).

    Raises:
        ConfigError: no such ladder; the message lists the ladders there are.
    """
    known = available_ladders()
    if ladder not in known:
        raise ConfigError(f"${{ladder}} {ladder!r}: no such severity ladder; ladders: "
                          f"{', '.join(known)} (each its -{', -'.join(RUNGS)} presets)")
    return [f"{ladder}-{rung}" for rung in RUNGS]


@dataclass
class Curve:
    """One network's curve over one ladder in one mode: per point (the clean frames, then each
    rung) AEE(f, f̌) and EPE against the ground truth, in pixels (None: not finished, or no
    ground truth)."""

    ladder: str
    network: str
    mode: str
    points: list = field(default_factory=list)          # ("clean" | preset, aee, epe)

    @property
    def rungs(self) -> list:
        return self.points[1:]

    def robustness(self) -> Optional[float]:
        """R: the mean AEE(f, f̌) over the rungs; None until every rung has it."""
        values = [aee for _, aee, _ in self.rungs]
        if not values or any(v is None for v in values):
            return None
        return sum(values) / len(values)

    def relative_error(self) -> Optional[float]:
        """RCE: the mean over the rungs of EPE_s − EPE_clean; None until every rung (and the
        clean frames) have an EPE."""
        clean = self.points[0][2] if self.points else None
        values = [epe for _, _, epe in self.rungs]
        if clean is None or not values or any(v is None for v in values):
            return None
        return sum(v - clean for v in values) / len(values)


def ladder_curves(rows: Sequence[dict], ladders: Sequence[str],
                  networks: Sequence[str]) -> list[Curve]:
    """The curves of every ladder, network and mode (in that order) from the grid's result rows
    (:func:`~weathergen.benchmark.collect_results`). The clean point of a network is read from
    any of its finished rungs (every run measures the clean frames: ``epe_benign``)."""
    index = {(r["network"], r["label"]): r for r in rows if r["kind"] == "weather"}
    curves = []
    for ladder in ladders:
        presets = ladder_presets(ladder)
        for net in networks:
            runs = [index.get((net, p)) or {} for p in presets]
            clean = next((r["epe_benign"] for r in runs if r.get("epe_benign") is not None), None)
            for mode, (aee_key, epe_key) in MODES.items():
                points = [("clean", 0.0 if any(r.get(aee_key) is not None for r in runs) else None,
                           clean)]
                points += [(p, r.get(aee_key), r.get(epe_key)) for p, r in zip(presets, runs)]
                curves.append(Curve(ladder, net, mode, points))
    return curves


def curve_rows(curves: Sequence[Curve]) -> list[dict]:
    """The curves as flat rows (``ladders.csv``): ladder, network, mode, point (0 clean, then
    1 ... S), label, aee, epe."""
    return [{"ladder": c.ladder, "network": c.network, "mode": c.mode, "point": i, "label": label,
             "aee": aee, "epe": epe}
            for c in curves for i, (label, aee, epe) in enumerate(c.points)]


def score_rows(curves: Sequence[Curve]) -> list[dict]:
    """One row per ladder, network and mode (``robustness.csv``): the clean EPE (accuracy), the
    robustness score R and the relative corruption error RCE, and how many rungs finished."""
    return [{"ladder": c.ladder, "network": c.network, "mode": c.mode,
             "epe_clean": c.points[0][2] if c.points else None,
             "robustness": c.robustness(), "relative_error": c.relative_error(),
             "rungs_done": sum(aee is not None for _, aee, _ in c.rungs), "rungs": len(c.rungs)}
            for c in curves]
