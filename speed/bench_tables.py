"""Table-scale benchmark: pair-steps per second of every network's attack, and the GPU-hours of the
paper's Tables 2-5 on Sintel.

What one *pair-step* is: one evaluation of the weather attack for one frame pair, as
:func:`weathergen.attack.attack_batch` repeats it (render the pair's particles, the network's
forward pass, the loss, the backward pass, one Adam update), timed through the same
:class:`~weathergen.attack.BatchOptimisation`. A pair attacked for ``S`` steps costs ``S + 1``
pair-steps (step 0 is evaluated too). For every network this script

1. measures the attack's pair-steps per second on the device at growing batch sizes (stopping at
   out-of-memory, at ``--memory-gib``, or when the throughput grows by less than 5 %), in each
   asked-for precision: ``paper`` (mixed precision where the paper ran the network in it:
   :attr:`ModelSpec.amp`), ``float32`` (no autocast; torch's defaults, so cuDNN convolutions in
   TF32 and matrix products in float32), ``amp`` (the network's mixed-precision mode, where it has
   one), ``tf32`` (float32 with matrix products in TF32 too); and, at the best batch, the network
   alone (its forward + backward on fixed frames: what the render and the loss add is the rest)
   and the forward pass alone (pairs per second, for Table 2);
2. counts the pair-steps (and forward passes) of the paper's tables (:func:`paper_runs`) and
   divides: GPU-hours per table, per network, in total.

The counts (from the paper and ``presets/attacks/supplement.toml``): Sintel train has 1041 pairs
(23 scenes, 1064 frames), Sintel-tr115 115 (the first five pairs of each scene); every weather
attack runs 750 Adam steps (751 pair-steps per pair); PCFA runs 20 L-BFGS steps of up to 10
evaluations (at most 201 per pair), I-FGSM 25 steps (26).

- Table 2 (random weather, Sintel train): 19 configurations, forward passes only, plus one
  forward pass for the clean flow of each pair;
- Table 3 (optimisation variables, Sintel-tr115): the seven ``grey-*`` configurations;
- Table 4 (weather attacks, Sintel-tr115): snow, rain, sparks, fog;
- Table 5 (against Lp attacks, Sintel train): PCFA, I-FGSM and snow. The Lp attacks render no
  weather; they are counted at the weather attack's throughput (the render is a few per cent of a
  step; the network-alone column bounds the difference).

    python speed/bench_tables.py --device cuda                     # measure, every network
    python speed/bench_tables.py --device cuda --models raft gma --precisions paper float32
    python speed/bench_tables.py --dry-run                         # the arithmetic only
    python speed/bench_tables.py --dry-run --assume raft=36.1 flowformer=3.2/9.0
    python speed/bench_tables.py --device cpu --quick              # smoke test, tiny sizes
    python speed/bench_tables.py --from-figures                    # every measured precision

``--from-figures`` measures nothing either: it prints the GPU-hours of every network in every
precision the GPU session measured (``--session``, default docs/figures/gpu-session.json; a
network only ``make gpu-check`` measured, in its paper precision), each with every step and with
early stopping: the weather attacks' pair-steps times the share of the steps an attack with
``--early-stop`` ran (``speed/bench_early_stop.py``'s figure in ``--bench``, the CPU figures
file; ``--step-fraction`` instead), and the distance of the fastest accepted precisions to the
4-hour goal of Table 4.

``--dry-run`` measures nothing: the throughputs come from ``--assume NET=STEPS[/FORWARD]``
(pair-steps per second of the attack [/ pairs per second of the forward pass]) and, for networks
not named there, from the figures file of ``make gpu-check`` (``--figures``; a network's attack
rows where it has them, else one pair's forward + backward and forward). Prints Markdown tables;
``--json PATH`` writes every figure (a dict: ``machine``, ``throughput``, ``counts``, ``hours``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "speed"))
sys.path.insert(1, str(ROOT))           # the source checkout before an installed copy

import bench_common  # noqa: E402  (the clock)

#: The paper's six networks, in its tables' order.
PAPER_NETWORKS = ("flownet2", "flownetcrobust", "spynet", "raft", "gma", "flowformer")
#: Pairs of Sintel's training set (23 scenes, 1064 frames) and of Sintel-tr115.
SINTEL_TRAIN_PAIRS = 1041
SINTEL_TR115_PAIRS = 115
#: Table 2's configurations: the bundled presets of these families (19 in all).
TABLE2_FAMILIES = ("particles-", "motion-blur-", "additive-", "size-")
#: Table 4's weather.
TABLE4_PRESETS = ("snow", "rain", "sparks", "fog")
#: ``paper`` and ``amp`` (fp16 in the network's own regions), then ``--precision``'s choices.
PRECISIONS = ("paper", "float32", "amp", "tf32", "bf16", "fp16")
#: A larger batch must raise the throughput by this much to count.
MIN_GAIN = 1.05
DEFAULT_FIGURES = ROOT / "docs" / "figures" / "gpu-check.json"
DEFAULT_SESSION = ROOT / "docs" / "figures" / "gpu-session.json"
DEFAULT_BENCH = ROOT / "docs" / "figures" / "bench.json"


# -- the counts --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Run:
    """One configuration of a table: ``pairs`` frame pairs, ``passes`` network evaluations per
    pair, with a backward pass (attack steps) or forward only."""

    table: str
    label: str
    pairs: int
    passes: int
    backward: bool = True
    stoppable: bool = False     # a weather attack, which --early-stop may end before its last step

    @property
    def pair_steps(self) -> int:
        return self.pairs * self.passes


def paper_runs() -> list[Run]:
    """Every configuration of the paper's Tables 2-5 with its network evaluations (see module)."""
    from weathergen.attack import ATTACK_CONFIGS, DEFAULT_STEPS, LP_DEFAULTS
    from weathergen.attack.lp import PCFA_LBFGS_ITERATIONS
    from weathergen.engine import list_presets

    weather = DEFAULT_STEPS + 1
    table2 = [p for p in list_presets() if p.startswith(TABLE2_FAMILIES)]
    runs = [Run("2", "clean flow", SINTEL_TRAIN_PAIRS, 1, backward=False)]
    runs += [Run("2", p, SINTEL_TRAIN_PAIRS, 1, backward=False) for p in table2]
    runs += [Run("3", name, SINTEL_TR115_PAIRS, weather, stoppable=True)
             for name, c in ATTACK_CONFIGS.items() if c.preset == "grey"]
    runs += [Run("4", name, SINTEL_TR115_PAIRS, weather, stoppable=True) for name in TABLE4_PRESETS]
    runs += [Run("5", "pcfa", SINTEL_TRAIN_PAIRS,
                 LP_DEFAULTS["pcfa"]["steps"] * PCFA_LBFGS_ITERATIONS + 1),
             Run("5", "ifgsm", SINTEL_TRAIN_PAIRS, LP_DEFAULTS["ifgsm"]["steps"] + 1),
             Run("5", "snow", SINTEL_TRAIN_PAIRS, weather, stoppable=True)]
    return runs


def table_counts(runs: list[Run]) -> dict[str, dict[str, int]]:
    """Per table: pair-steps (with backward) and forward-only passes, per network."""
    out: dict[str, dict[str, int]] = {}
    for r in runs:
        t = out.setdefault(r.table, {"pair_steps": 0, "forward_passes": 0})
        t["pair_steps" if r.backward else "forward_passes"] += r.pair_steps
    return out


@dataclass(frozen=True)
class Throughput:
    """A network's attack throughput (pair-steps/s) and forward throughput (pairs/s)."""

    attack: float
    forward: Optional[float] = None
    source: str = ""


def table_hours(runs: list[Run], throughput: Throughput,
                step_fraction: float = 1.0) -> dict[str, float]:
    """GPU-hours per table (and ``total``) for one network at ``throughput``. A forward-only run
    without a forward throughput counts at the attack's (an upper bound). ``step_fraction``: the
    share of its pair-steps a weather attack runs (early stopping; 1: every step)."""
    out: dict[str, float] = {}
    for r in runs:
        rate = throughput.attack if r.backward else (throughput.forward or throughput.attack)
        share = step_fraction if r.stoppable else 1.0
        out[r.table] = out.get(r.table, 0.0) + share * r.pair_steps / rate / 3600.0
    out["total"] = sum(out.values())
    return out


def all_hours(runs: list[Run], throughputs: dict[str, Throughput]) -> dict[str, dict[str, float]]:
    """:func:`table_hours` of every network, and ``all`` (their sum per table)."""
    out = {name: table_hours(runs, tp) for name, tp in throughputs.items()}
    tables = sorted({r.table for r in runs}) + ["total"]
    out["all"] = {t: sum(h[t] for h in out.values()) for t in tables}
    return out


def hours_table(hours: dict[str, dict[str, float]], title: str) -> str:
    """Markdown: a row per network, a column per table, the total."""
    tables = [t for t in next(iter(hours.values())) if t != "total"]
    head = ["network"] + [f"Table {t}" for t in tables] + ["total"]
    lines = [title, "", "| " + " | ".join(head) + " |", "|---" + "|---:" * (len(head) - 1) + "|"]
    for name, h in hours.items():
        cells = [f"{h[t]:.1f}" for t in tables] + [f"**{h['total']:.1f}**"]
        lines.append(f"| {'all networks' if name == 'all' else name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def needed_for(target_hours: float, pair_steps: int) -> float:
    """Pair-steps per second every network would need for ``pair_steps`` each, all networks
    together in ``target_hours`` (the sum of 1 / throughput over the networks)."""
    return pair_steps / (target_hours * 3600.0)


# -- assumed throughputs (dry run) -------------------------------------------------------------

def figures_throughputs(path: Path) -> dict[str, Throughput]:
    """Throughputs read from a ``make gpu-check`` figures file: a network's best ``attack batch``
    row where it has one, else 1 / (one pair's forward + backward), and 1 / (its forward)."""
    data = json.loads(Path(path).read_text())
    where = data.get("title", str(path))
    attack: dict[str, float] = {}
    fwd_bwd: dict[str, float] = {}
    fwd: dict[str, float] = {}
    for row in data.get("rows", []):
        what, seconds = row.get("what", ""), row.get("seconds")
        if row.get("failed") or not seconds:
            continue
        m = re.match(r"(\S+), batch of (\d+): a step$", what)
        if row.get("area") == "attack batch" and m:
            attack[m[1]] = max(attack.get(m[1], 0.0), int(m[2]) / seconds)
        m = re.match(r"(\S+), (forward \+ backward|forward)$", what)
        if row.get("area") == "networks" and m:
            (fwd_bwd if m[2] != "forward" else fwd)[m[1]] = 1.0 / seconds
    out = {}
    for name in set(attack) | set(fwd_bwd):
        if name in attack:
            out[name] = Throughput(attack[name], fwd.get(name),
                                   f"{where}: attack batch rows")
        else:
            out[name] = Throughput(fwd_bwd[name], fwd.get(name),
                                   f"{where}: one pair's forward + backward")
    return out


def parse_assume(items: list[str]) -> dict[str, Throughput]:
    """``NET=STEPS`` or ``NET=STEPS/FORWARD`` -> throughputs (ValueError naming a bad item)."""
    out = {}
    for item in items:
        m = re.fullmatch(r"([\w.-]+)=([0-9.eE+-]+)(?:/([0-9.eE+-]+))?", item.strip())
        try:
            attack = float(m[2]) if m else math.nan
            forward = float(m[3]) if m and m[3] else None
        except ValueError:
            attack = math.nan
        if not m or not attack > 0 or (forward is not None and not forward > 0):
            raise ValueError(f"--assume {item!r}: expected NET=STEPS or NET=STEPS/FORWARD "
                             f"with positive numbers (pair-steps/s, pairs/s)")
        out[m[1]] = Throughput(attack, forward, "assumed (--assume)")
    return out


# -- measuring --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Options:
    """What a measurement switches on besides the precision (see docs/scale.md)."""

    checkpointing: bool = False
    compile: Optional[str] = None       # torch.compile mode of the iteration steps, or None
    backend: str = "inductor"           # torch.compile's backend (aot_eager: a quick smoke test)

    def label(self) -> str:
        parts = (["checkpointing"] if self.checkpointing else []) + \
            ([f"compile={self.compile}"] if self.compile else [])
        return ", ".join(parts) or "-"


@dataclass(frozen=True)
class Sizes:
    width: int = 1024
    height: int = 436
    iters: Optional[int] = None          # None: each network's default
    count: Optional[int] = None          # particles per pair (None: the preset's)
    batch_sizes: tuple = (1, 2, 4, 8, 16, 32)
    steps: int = 3                       # timed steps per batch size (the median counts)


QUICK = Sizes(width=128, height=64, iters=2, count=100, batch_sizes=(1, 2), steps=1)


@dataclass
class Measured:
    """One network in one precision with one set of options: the throughput at each batch tried
    and what happened at the end (``stop``)."""

    network: str
    precision: str
    options: str
    batches: dict = field(default_factory=dict)   # batch -> {step_seconds, pair_steps_per_second, memory_gib}
    best_batch: Optional[int] = None
    attack: Optional[float] = None                 # pair-steps/s at the best batch
    network_share: Optional[float] = None          # network fwd+bwd alone / a whole step
    forward: Optional[float] = None                # pairs/s, forward only, at the best batch
    stop: str = ""
    seconds: float = 0.0                           # wall time of the measurement


def _is_oom(exc: BaseException) -> bool:
    import torch

    return isinstance(exc, torch.cuda.OutOfMemoryError) or "out of memory" in str(exc).lower()


def precision_settings(name: str, precision: str, device: str, anywhere: bool = False) -> str:
    """The :attr:`FlowModel.precision` a measured precision sets for network ``name`` on
    ``device``: ``paper`` (fp16 where the paper ran the network in mixed precision, else float32),
    ``amp`` (fp16 in the network's own mixed-precision regions), ``float32``, ``tf32``, ``bf16``,
    ``fp16`` (``--precision``). ValueError where it does not apply: amp for a network without a
    mixed-precision mode, a precision refused for the network, amp or tf32 off CUDA
    (``anywhere``: allowed there too, where they change nothing or run on the CPU: a smoke test
    of the code path)."""
    from weathergen.errors import ConfigError
    from weathergen.models import model_spec, resolve_amp, resolve_precision

    cuda = device.startswith("cuda") or anywhere
    if precision == "paper":
        return "fp16" if resolve_amp(name, None, device) else "float32"
    if precision in ("amp", "tf32") and not cuda:
        raise ValueError(f"{precision} needs a CUDA device")
    if precision == "amp":
        if not model_spec(name).mixed_precision:
            raise ValueError(f"{name} has no mixed-precision mode")
        return "fp16"
    if precision not in PRECISIONS:
        raise ValueError(f"unknown precision {precision!r}")
    try:
        return resolve_precision(name, precision, None, "cuda" if cuda else device)
    except ConfigError as exc:
        raise ValueError(str(exc)) from None


class Bench:
    """The frame pair and particle records every measurement on one device shares."""

    def __init__(self, device: str, sizes: Sizes, preset: str = "snow"):
        from bench_attack import synthetic_pair
        from weathergen.engine import load_preset, sample_particles

        self.device, self.sizes = device, sizes
        self.pair = synthetic_pair(sizes.width, sizes.height)
        overrides = {"count": sizes.count} if sizes.count else None
        p = load_preset(preset, overrides)
        self.records = [sample_particles(self.pair, p, seed=i)
                        for i in range(max(sizes.batch_sizes))]

    def model(self, name: str, precision: str, options: Options):
        from weathergen.models import build_model, compile_iterations

        model = build_model(name, iters=self.sizes.iters,
                            gradient_checkpointing=options.checkpointing).to(self.device)
        model.requires_grad_(False)
        model.precision = precision
        if options.compile:
            compile_iterations(model, options.compile, options.backend)
        return model

    def step(self, model, batch: int):
        """One attack step of ``batch`` pairs as a call, and the optimisation it runs."""
        from weathergen.attack import AttackSettings, BatchOptimisation

        run = BatchOptimisation(model, [self.pair] * batch, self.records[:batch],
                                AttackSettings(), device=self.device)

        def step():
            losses = run.evaluate()[2]
            run.update(losses.sum())

        return step, run

    def network_alone(self, model, run) -> Callable[[], object]:
        """The network's forward + backward on the batch's weather frames (fixed), with the
        attack's distance as the loss: what a step costs without render, penalty and update."""
        import torch

        from weathergen.flow import aee

        with torch.no_grad():
            out = run.render([v.particles() for v in run.variables])
        a, b = out.image1.detach(), out.image2.detach()

        def once():
            x1, x2 = a.clone().requires_grad_(True), b.clone().requires_grad_(True)
            aee(model(x1, x2), run.goal).sum().backward()

        return once

    def forward_only(self, model, run) -> Callable[[], object]:
        import torch

        def once():
            with torch.no_grad():
                model(run.frames["image1"], run.frames["image2"])

        return once


def measure(bench: Bench, name: str, precision: str, options: Options = Options(),
            budget_s: float = math.inf, log: Callable[[str], None] = lambda s: None,
            anywhere: bool = False, batch_sizes: Optional[tuple] = None) -> Measured:
    """Throughput of ``name``'s attack on the bench's device at growing batch sizes (see module).
    Stops trying larger batches at out-of-memory, when the throughput grows by less than
    :data:`MIN_GAIN`, or once ``budget_s`` seconds have passed. ``batch_sizes``: those to try
    (default: the bench's; at most its largest)."""
    import torch

    start = time.perf_counter()
    setting = precision_settings(name, precision, bench.device, anywhere)
    result = Measured(name, precision, options.label())
    cuda = bench.device.startswith("cuda")
    old_tf32 = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = setting == "tf32"   # the backward passes too
    model = run = best_run = None
    try:
        model = bench.model(name, setting, options)
        for batch in batch_sizes or bench.sizes.batch_sizes:
            if time.perf_counter() - start > budget_s:
                result.stop = f"time budget ({budget_s:.0f} s) spent before batch {batch}"
                break
            try:
                if cuda:
                    torch.cuda.empty_cache()
                    torch.cuda.reset_peak_memory_stats(bench.device)
                step, run = bench.step(model, batch)
                seconds = bench_common.timed(step, bench.device, bench.sizes.steps)
            except Exception as exc:      # noqa: BLE001 - out of memory is an answer here
                run = None
                if not _is_oom(exc):
                    raise
                result.stop = f"out of memory at batch {batch}"
                break
            memory = torch.cuda.max_memory_allocated(bench.device) / 2**30 if cuda else None
            rate = batch / seconds
            result.batches[batch] = {"step_seconds": seconds, "pair_steps_per_second": rate,
                                     "memory_gib": memory}
            log(f"  {name} [{precision}; {options.label()}] batch {batch}: {seconds:.3f} s/step, "
                f"{rate:.2f} pair-steps/s" + (f", {memory:.1f} GiB" if memory else ""))
            if result.attack is not None and rate < result.attack * MIN_GAIN:
                if rate > result.attack:
                    result.attack, result.best_batch, best_run = rate, batch, run
                result.stop = f"throughput grew by less than {MIN_GAIN - 1:.0%} at batch {batch}"
                break
            if result.attack is None or rate > result.attack:
                result.attack, result.best_batch, best_run = rate, batch, run
            run = None
        else:
            result.stop = "largest batch size tried"
        if best_run is not None:
            best = result.batches[result.best_batch]["step_seconds"]
            timed = bench_common.timed
            alone = timed(bench.network_alone(model, best_run), bench.device, bench.sizes.steps)
            result.network_share = alone / best
            result.forward = result.best_batch / timed(bench.forward_only(model, best_run),
                                                       bench.device, bench.sizes.steps)
    finally:
        torch.backends.cuda.matmul.allow_tf32 = old_tf32
        del model, run, best_run
        if cuda:
            torch.cuda.empty_cache()
    result.seconds = time.perf_counter() - start
    return result


def measured_table(results: list[Measured]) -> str:
    lines = ["| network | precision | options | best batch | pair-steps/s | network alone "
             "(share of a step) | forward pairs/s | batches tried (pair-steps/s) | stop |",
             "|---|---|---|---:|---:|---:|---:|---|---|"]
    for r in results:
        tried = ", ".join(f"{b}: {v['pair_steps_per_second']:.2f}" for b, v in r.batches.items())
        share = "–" if r.network_share is None else f"{r.network_share:.0%}"
        fwd = "–" if r.forward is None else f"{r.forward:.2f}"
        rate = "–" if r.attack is None else f"{r.attack:.2f}"
        lines.append(f"| {r.network} | {r.precision} | {r.options} | {r.best_batch or '–'} | "
                     f"{rate} | {share} | {fwd} | {tried} | {r.stop} |")
    return "\n".join(lines)


def device_name(device: str) -> str:
    import torch

    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    return f"CPU ({os.cpu_count()} cores, {torch.get_num_threads()} torch thread(s))"


def cap_memory(device: str, gib: Optional[float]) -> None:
    """Let torch allocate at most ``gib`` GiB on a CUDA ``device`` (e.g. 78 on a larger GPU, to
    find the batch sizes of an 80 GB H100)."""
    import torch

    if gib and device.startswith("cuda"):
        total = torch.cuda.get_device_properties(torch.device(device)).total_memory / 2**30
        torch.cuda.set_per_process_memory_fraction(min(1.0, gib / total), torch.device(device).index or 0)


def run_measurements(device: str, sizes: Sizes, networks, precisions, options: Options,
                     budget_s: float, log: Callable[[str], None] = print) -> list[Measured]:
    """Measure every network in every precision that applies to it."""
    bench = Bench(device, sizes)
    results = []
    for name in networks:
        for precision in precisions:
            try:
                precision_settings(name, precision, device)
            except ValueError as exc:
                log(f"  {name} [{precision}]: skipped ({exc})")
                continue
            if precision != "paper" and "paper" in precisions and \
                    precision_settings(name, "paper", device) == precision_settings(name, precision, device):
                log(f"  {name} [{precision}]: the same as its paper precision")
                continue
            try:
                results.append(measure(bench, name, precision, options, budget_s, log))
            except Exception as exc:      # noqa: BLE001 - one network's failure hides no other
                r = Measured(name, precision, options.label(), stop=f"failed: "
                             f"{type(exc).__name__}: {exc}"[:200])
                results.append(r)
                log(f"  {name} [{precision}]: {r.stop}")
    return results


def best_throughputs(results: list[Measured], precision: str) -> dict[str, Throughput]:
    """Per network, the measured throughput in ``precision`` (the paper's precision falls back on
    float32 where only that was measured)."""
    out = {}
    for r in results:
        if r.attack is None:
            continue
        if r.precision == precision or (precision == "paper" and r.precision == "float32"
                                        and r.network not in out):
            out[r.network] = Throughput(r.attack, r.forward,
                                        f"measured, {r.precision}, batch {r.best_batch}")
    return out


# -- from the figures files: every measured precision, with and without early stopping ---------------

def session_throughputs(path: Path) -> dict[str, dict[str, Throughput]]:
    """``{precision: {network: Throughput}}`` from a GPU session's JSON file: the rows of its
    ``tables`` and ``options`` sections measured without options, each under the precision it
    sets (``paper``: fp16 for GMA, float32 for the others; ``amp``: fp16), the best where two
    rows give one. A precision refused for a network is left out."""
    data = json.loads(Path(path).read_text())
    gpu = data.get("machine", {}).get("gpu", "a GPU")
    sections = data.get("sections", {})
    rows = sections.get("tables", {}).get("measured", []) + sections.get("options", {}).get("rows", [])
    out: dict[str, dict[str, Throughput]] = {}
    for r in rows:
        if r.get("options", "-") != "-" or not r.get("attack"):
            continue
        try:
            precision = precision_settings(r["network"], r["precision"], "cuda")
        except ValueError:
            continue
        known = out.setdefault(precision, {}).get(r["network"])
        if known is None or r["attack"] > known.attack:
            out[precision][r["network"]] = Throughput(
                r["attack"], r.get("forward"), f"{gpu}, measured as {r['precision']}, batch "
                                               f"{r.get('best_batch')}")
    return out


def step_fractions(path: Path) -> dict[str, float]:
    """Per network, the share of the full budget's pair-steps an attack with early stopping ran:
    the ``figures:`` line of ``speed/bench_early_stop.py``'s section of the figures file, its
    networks with trained weights only (random weights' flat losses say nothing of a trained
    network's)."""
    sections = json.loads(Path(path).read_text()).get("sections", {}) if Path(path).exists() else {}
    for command, section in sections.items():
        if "bench_early_stop.py" in command:
            for line in section.get("output", "").splitlines():
                if line.startswith("figures: "):
                    return {n: f["step_fraction"] for n, f in json.loads(line[9:]).items()
                            if f.get("weights") != "random weights"}
    return {}


def precision_hours(runs: list[Run], by_precision: dict[str, dict[str, Throughput]],
                    fractions: dict[str, float]) -> list[dict]:
    """One row per network and precision: its throughput and its GPU-hours of Table 4 and of all
    tables, with every step and with early stopping (the network's measured step fraction, else
    the mean of those measured; 1 where none is)."""
    mean = sum(fractions.values()) / len(fractions) if fractions else 1.0
    rows = []
    for precision, throughputs in by_precision.items():
        for name, tp in throughputs.items():
            fraction = fractions.get(name, mean)
            full, early = table_hours(runs, tp), table_hours(runs, tp, fraction)
            rows.append({"network": name, "precision": precision, "pair_steps_per_second": tp.attack,
                         "step_fraction": fraction, "measured_fraction": name in fractions,
                         "fraction_of": name if name in fractions else ", ".join(fractions) or "-",
                         "table4": full["4"], "total": full["total"],
                         "table4_early": early["4"], "total_early": early["total"],
                         "source": tp.source})
    return sorted(rows, key=lambda r: (PAPER_NETWORKS + (r["network"],)).index(r["network"]))


def fastest(rows: list[dict]) -> dict[str, dict]:
    """Per network, its row of the fewest GPU-hours (its fastest accepted precision)."""
    best: dict[str, dict] = {}
    for r in rows:
        if r["network"] not in best or r["total"] < best[r["network"]]["total"]:
            best[r["network"]] = r
    return best


def precision_report(rows: list[dict], target_hours: float = 4.0) -> str:
    """The table of :func:`precision_hours` and the distance of the fastest precisions to the
    goal of ``target_hours`` for Table 4."""
    lines = ["| network | precision | pair-steps/s | Table 4 h | all tables h | steps run with "
             "early stopping | Table 4 h, early stopping | all tables h, early stopping |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        share = f"{r['step_fraction']:.0%}" + ("" if r["measured_fraction"] else
                                               f" (of {r['fraction_of']})")
        lines.append(f"| {r['network']} | {r['precision']} | {r['pair_steps_per_second']:.2f} | "
                     f"{r['table4']:.1f} | {r['total']:.1f} | {share} | {r['table4_early']:.1f} | "
                     f"{r['total_early']:.1f} |")
    best = fastest(rows)
    t4, t4_early = (sum(r[k] for r in best.values()) for k in ("table4", "table4_early"))
    choice = ", ".join(f"{n} {r['precision']}" for n, r in best.items())
    lines += ["", f"Fastest accepted precision per network ({choice}): Table 4 takes {t4:.1f} "
                  f"GPU-hours, {t4 / target_hours:.1f}x the goal of {target_hours:g} hours; with "
                  f"early stopping {t4_early:.1f} GPU-hours, {t4_early / target_hours:.1f}x."]
    return "\n".join(lines)


# -- the command ----------------------------------------------------------------------------------

def report(runs: list[Run], throughputs: dict[str, Throughput], title: str,
           target_hours: float = 4.0) -> tuple[str, dict]:
    """The printed hours table and its figures for one set of throughputs."""
    hours = all_hours(runs, throughputs)
    counts = table_counts(runs)
    text = [hours_table(hours, title), ""]
    t4 = counts["4"]["pair_steps"]
    need = sum(1.0 / tp.attack for tp in throughputs.values())
    budget = target_hours * 3600.0 / t4
    text.append(f"Table 4 ({t4:,} pair-steps per network) for these {len(throughputs)} networks: "
                f"{hours['all']['4']:.1f} GPU-hours; {target_hours:g} hours allow "
                f"{budget * 1000:.1f} ms per pair-step summed over the networks, these take "
                f"{need * 1000:.1f} ms ({need / budget:.1f}x the target).")
    for name, tp in throughputs.items():
        text.append(f"- {name}: {tp.attack:.2f} pair-steps/s"
                    + (f", forward {tp.forward:.2f} pairs/s" if tp.forward else "")
                    + f" ({tp.source})")
    figures = {"throughput": {n: dataclasses.asdict(tp) for n, tp in throughputs.items()},
               "hours": hours, "target_hours_table4": target_hours,
               "table4_ms_per_pair_step_allowed": budget * 1000,
               "table4_ms_per_pair_step_summed": need * 1000}
    return "\n".join(text), figures


def report_hours(runs: list[Run], results: list[Measured], precisions, title: str,
                 target_hours: float = 4.0) -> dict:
    """Print the GPU-hours report (``TITLE, PRECISION``) of each precision in ``precisions`` that
    has measured throughputs, and return their figures by precision."""
    out = {}
    for precision in precisions:
        tps = best_throughputs(results, precision)
        if tps:
            text, hours = report(runs, tps, f"{title}, {precision}", target_hours)
            print(text + "\n", flush=True)
            out[precision] = hours
    return out


def counts_table(runs: list[Run]) -> str:
    counts = table_counts(runs)
    lines = ["Network evaluations per network (pair-steps: forward + backward; forward: "
             "forward only):", "", "| table | runs | pair-steps | forward passes |",
             "|---|---:|---:|---:|"]
    for t, c in counts.items():
        n = sum(1 for r in runs if r.table == t)
        lines.append(f"| {t} | {n} | {c['pair_steps']:,} | {c['forward_passes']:,} |")
    return "\n".join(lines)


def from_figures(runs: list[Run], session: Path, check: Path, bench: Path,
                 step_fraction: Optional[float], target_hours: float) -> dict:
    """``--from-figures``: print the GPU-hours of every network in every precision measured in
    the GPU session (networks measured only by ``make gpu-check``: in their paper precision), with
    and without early stopping; return the figures."""
    by_precision = session_throughputs(session) if session.exists() else {}
    seen = {n for tps in by_precision.values() for n in tps}
    for name, tp in (figures_throughputs(check) if check.exists() else {}).items():
        if name not in seen and name in PAPER_NETWORKS:
            by_precision.setdefault(precision_settings(name, "paper", "cuda"), {})[name] = tp
    fractions = step_fractions(bench) if step_fraction is None else {
        n: step_fraction for tps in by_precision.values() for n in tps}
    rows = precision_hours(runs, by_precision, fractions)
    print(f"GPU-hours per network and precision, from {session.name} and {check.name} (GPU "
          f"figures measured on an earlier tree: not measured on this tree), early stopping's "
          f"step fraction from "
          f"{'--step-fraction' if step_fraction is not None else bench.name + ' (bench_early_stop.py)'}"
          f"{'' if fractions else ': none measured, every step counted'}:\n")
    print(precision_report(rows, target_hours))
    missing = not_measured(by_precision)
    print("\nNot measured on a GPU (no row in these files): "
          + "; ".join(f"{n} {', '.join(ps)}" for n, ps in missing.items()))
    return {"rows": rows, "step_fractions": fractions, "not_measured": missing}


def not_measured(by_precision: dict[str, dict[str, Throughput]]) -> dict[str, list[str]]:
    """Per paper network, the precisions it accepts that have no measured throughput."""
    from weathergen.models import PRECISIONS as ACCEPTED, model_spec

    return {n: [p for p in ACCEPTED if p not in model_spec(n).refused_precisions
                and n not in by_precision.get(p, {})] for n in PAPER_NETWORKS}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda", help="cuda, cuda:N or cpu")
    parser.add_argument("--models", nargs="+", default=list(PAPER_NETWORKS))
    parser.add_argument("--precisions", nargs="+", default=["paper", "float32"],
                        choices=PRECISIONS)
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=None)
    parser.add_argument("--steps", type=int, default=None, help="timed steps per batch size")
    parser.add_argument("--checkpointing", action="store_true",
                        help="gradient checkpointing (recompute the iterations in backward)")
    parser.add_argument("--compile", default=None,
                        choices=["default", "reduce-overhead", "max-autotune-no-cudagraphs"],
                        help="torch.compile the networks' iteration steps in this mode")
    parser.add_argument("--memory-gib", type=float, default=None,
                        help="let torch use at most this much GPU memory (78: an H100's)")
    parser.add_argument("--budget-s", type=float, default=math.inf,
                        help="seconds per network and precision before larger batches are skipped")
    parser.add_argument("--target-hours", type=float, default=4.0)
    parser.add_argument("--dry-run", action="store_true", help="the arithmetic only")
    parser.add_argument("--assume", nargs="+", default=[],
                        help="NET=STEPS[/FORWARD] throughputs for --dry-run")
    parser.add_argument("--figures", type=Path, default=DEFAULT_FIGURES,
                        help="a make gpu-check figures file for --dry-run")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (a smoke test)")
    parser.add_argument("--from-figures", action="store_true",
                        help="the hours of every precision measured in --session (and --figures), "
                             "with and without early stopping (--bench's step saving)")
    parser.add_argument("--session", type=Path, default=DEFAULT_SESSION,
                        help="a GPU session's JSON file for --from-figures")
    parser.add_argument("--bench", type=Path, default=DEFAULT_BENCH,
                        help="the CPU figures file holding bench_early_stop.py's step saving")
    parser.add_argument("--step-fraction", type=float, default=None,
                        help="share of the weather attacks' steps run with early stopping "
                             "(instead of --bench's)")
    parser.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = parser.parse_args(argv)

    runs = paper_runs()
    figures: dict = {"counts": table_counts(runs),
                     "runs": [dataclasses.asdict(r) for r in runs]}
    print(counts_table(runs) + "\n")
    if args.from_figures:
        figures["from_figures"] = from_figures(runs, args.session, args.figures, args.bench,
                                               args.step_fraction, args.target_hours)
    elif args.dry_run:
        try:
            given = parse_assume(args.assume)
        except ValueError as exc:
            print(exc, file=sys.stderr)
            return 2
        known = figures_throughputs(args.figures) if args.figures.exists() else {}
        throughputs = {n: given.get(n) or known.get(n) for n in args.models}
        missing = [n for n, tp in throughputs.items() if tp is None]
        if missing:
            print(f"--dry-run: no throughput for {', '.join(missing)} (give --assume "
                  f"{missing[0]}=STEPS, or a --figures file that has it)", file=sys.stderr)
            return 2
        text, hours = report(runs, throughputs, "GPU-hours (assumed throughputs)",
                             args.target_hours)
        print(text)
        figures.update(machine="dry run (assumed throughputs)", dry_run=hours)
    else:
        import torch

        if args.device.startswith("cuda") and not torch.cuda.is_available():
            print("bench_tables: no CUDA device here (use --device cpu --quick for a smoke "
                  "test, or --dry-run)", file=sys.stderr)
            return 2
        sizes = QUICK if args.quick else Sizes()
        sizes = dataclasses.replace(sizes, **{k: v for k, v in (
            ("batch_sizes", tuple(args.batch_sizes) if args.batch_sizes else None),
            ("steps", args.steps)) if v})
        cap_memory(args.device, args.memory_gib)
        options = Options(args.checkpointing, args.compile)
        machine = f"{device_name(args.device)}, torch {torch.__version__}"
        print(f"Measuring on {machine}, {sizes.width}x{sizes.height}"
              + (" (quick: tiny sizes, the figures mean nothing)" if args.quick else ""),
              flush=True)
        results = run_measurements(args.device, sizes, args.models, args.precisions, options,
                                   args.budget_s, log=lambda s: print(s, flush=True))
        print("\n" + measured_table(results) + "\n")
        figures.update(machine=machine, size=[sizes.width, sizes.height], quick=args.quick,
                       measured=[dataclasses.asdict(r) for r in results])
        hours = report_hours(runs, results, args.precisions, f"GPU-hours on {machine}",
                             args.target_hours)
        if hours:
            figures["hours"] = hours
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
