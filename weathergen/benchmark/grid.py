"""The benchmark grid: networks × {random weather, adversarial weather, Lp attacks} × presets.

A grid is a list of :class:`Cell` runs. Every cell is one ordinary ``attack`` run (an
:class:`~weathergen.attack.AttackJob` handed to :func:`~weathergen.attack.run_attack`) into its
own folder ``OUT/runs/<network>/<label>``, so each is resumable and readable like any attack
output:

- one *weather* cell per network and preset: its ``aee_random`` (step 0: the random weather that
  ``render --seed S`` writes for the preset) fills the "augmentations" table and its
  ``aee_adversarial`` the "weatherattacks" table; a label that names an attack configuration of
  the supplement rather than a preset (``grey-offset1`` ...) is attacked with that configuration
  and fills the "optimvariables" table;
- one *Lp* cell per network and Lp method (``pcfa``, ``ifgsm``): its ``aee_adversarial`` fills
  the "of_attacks" table, next to the adversarial snow of the same network;
- with ladders (``ladders``, :mod:`.ladder`), one weather cell per network and rung of each
  ladder (``snow-light`` ...), which fill the ladder's curves and tables.

:func:`run_grid` runs the cells of one shard (``i/N`` takes every N-th cell) one after another
through ``execute`` — the place where another executor (worker pool, cluster) plugs in: it gets
the :class:`AttackJob` of a cell and must leave the cell's folder finished. Cells already
finished are skipped (``attack --resume`` semantics: a half-done cell continues at its next pair),
then the tables are written from the per-run ``summary.json`` files (:mod:`.tables`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Mapping, Optional, Sequence

from ..attack import (ATTACK_CONFIGS, LP_METHODS, AttackConfig, AttackJob, EarlyStop, job_model,
                      lp_pass_name, lp_settings, probe_job_network, run_attack)
from ..attack.plan import attack_pass_name, plan_attack
from ..datasets import Dataset, reopen_dataset
from ..engine import list_presets
from ..errors import ConfigError
from ..models import Network, resolve_network
from ..models.external import network_label
from ..models.registry import renamed
from ..models.checkpoints import sha256_of
from .ladder import ladder_presets

#: The paper's four weather presets and its two Lp baselines.
DEFAULT_PRESETS = ("snow", "rain", "sparks", "fog")
DEFAULT_LP = ("pcfa", "ifgsm")
#: Pairs per scene of the paper's Sintel-tr115 selection, the benchmark's default.
TR115_FRAMES_PER_SCENE = 5
#: The paper's names for its six networks (table columns, the plot's legend); others keep theirs.
PAPER_NAMES = {"flownet2": "FN2", "flownetcrobust": "FNCR", "spynet": "SpyNet", "raft": "RAFT",
               "gma": "GMA", "flowformer": "FF"}


def network_name(name: str) -> str:
    """A network as the paper's tables name it (a network of your own by its short label,
    ``stem.NAME``)."""
    return PAPER_NAMES.get(name) or network_label(name)


@dataclass(frozen=True)
class Cell:
    """One run of the grid: ``kind`` is ``weather`` (label = preset) or ``lp`` (label = method)."""

    network: str
    kind: str
    label: str

    def folder(self, out: Path) -> Path:
        """``OUT/runs/<network>/<label>``; a network of your own under its short label
        (``stem.NAME``, :attr:`~weathergen.models.Network.label`)."""
        return Path(out) / "runs" / network_label(self.network) / self.label


@dataclass
class BenchmarkSpec:
    """What a benchmark runs. ``checkpoints`` maps a network to its checkpoint (None: its own);
    ``overrides`` are preset keys applied to every weather cell (``--set``); ``compat`` the
    weather attacks' terms (``paper`` or ``reference``, see :mod:`weathergen.attack.compat`).
    ``resolved``: each network's :class:`~weathergen.models.Network`, resolved once when the spec
    is made (given ones are kept). A network named twice, or a checkpoint for a network not in
    ``networks``, is refused."""

    dataset: Dataset
    out: Path
    networks: Sequence[str]
    presets: Sequence[str] = DEFAULT_PRESETS
    lp_methods: Sequence[str] = DEFAULT_LP
    checkpoints: Mapping[str, Optional[str]] = field(default_factory=dict)
    steps: Optional[int] = None          # weather attack steps (None: the attack's default)
    lp_steps: Optional[int] = None       # Lp steps (None: each method's default)
    iters: Optional[int] = None
    overrides: Mapping[str, str] = field(default_factory=dict)
    seed: int = 0
    device: str = "cpu"
    download: bool = False
    amp: Optional[bool] = None           # mixed precision; None: each network's paper setting
    precision: Optional[str] = None      # float32, tf32, bf16, fp16; None: as amp
    early_stop: Optional[EarlyStop] = None   # the weather attacks' convergence; None: every step
    command: list = field(default_factory=list)
    compat: str = "paper"                # the weather attacks' terms (paper or reference)
    #: severity ladders (``snow``: snow-light, snow-moderate, snow-heavy), their rungs run as
    #: weather cells after ``presets`` (:mod:`.ladder`)
    ladders: Sequence[str] = ()
    resolved: Mapping[str, Network] = field(default_factory=dict)

    def __post_init__(self):
        twice = sorted({n for n in self.networks if list(self.networks).count(n) > 1})
        if twice:
            raise ConfigError(f"${{networks}} names {', '.join(map(repr, twice))} twice")
        stray = [n for n in self.checkpoints if n not in self.networks]
        if stray:
            raise ConfigError(f"${{checkpoint}} {stray[0]}={self.checkpoints[stray[0]]}: "
                              f"{stray[0]!r} is not among ${{networks}} "
                              f"({', '.join(self.networks) or 'none'})")
        try:
            self.resolved = {n: self.resolved.get(n) or resolve_network(n) for n in self.networks}
        except ConfigError as exc:
            raise renamed(exc, "networks") from None

    def cells(self) -> list[Cell]:
        """Every run of the grid, in order. ConfigError names the benchmark's option of a
        method, preset or ladder it cannot run (before the attack's own checks would name the
        attack's options)."""
        if not self.networks:
            raise ConfigError("${networks} names no network")
        labels: dict = {}
        for net in self.networks:
            other = labels.setdefault(network_label(net), net)
            if other != net:
                raise ConfigError(f"${{networks}}: {other!r} and {net!r} would share the run "
                                  f"folder {network_label(net)!r}; name one of them otherwise")
        for method in self.lp_methods:
            if method not in LP_METHODS:
                raise ConfigError(f"${{lp}} {method!r}: expected {', '.join(LP_METHODS)}")
        labels = list(dict.fromkeys(self.presets))    # the presets, then the ladders' other rungs
        for ladder in self.ladders:
            labels += [p for p in ladder_presets(ladder) if p not in labels]
        if not labels and not self.lp_methods:
            raise ConfigError("the grid is empty: ${presets}, ${lp} and ${ladder} name nothing "
                              "to run")
        cells = []
        for net in self.networks:
            cells += [Cell(net, "weather", p) for p in labels]
            cells += [Cell(net, "lp", m) for m in self.lp_methods]
        return cells


def label_config(label: str) -> Optional[AttackConfig]:
    """The attack configuration a weather cell's label names, or None where it names a preset
    (a preset attacked under its own name still takes its configuration, e.g. fog's)."""
    if label in ATTACK_CONFIGS and label not in list_presets():
        return ATTACK_CONFIGS[label]
    return None


def tr115_default(dataset: Dataset) -> Dataset:
    """The selection with at most :data:`TR115_FRAMES_PER_SCENE` pairs per scene where it sets no
    limit of its own (the paper's Sintel-tr115 on Sintel's training split)."""
    if dataset.selection.frames_per_scene is not None:
        return dataset
    return reopen_dataset({**dataset.describe(), "frames_per_scene": TR115_FRAMES_PER_SCENE})


def cell_job(spec: BenchmarkSpec, cell: Cell) -> AttackJob:
    """The attack run of one cell (resuming whatever its folder holds)."""
    common = dict(dataset=spec.dataset, out=cell.folder(spec.out), model=spec.resolved[cell.network],
                  checkpoint=spec.checkpoints.get(cell.network), iters=spec.iters,
                  seed=spec.seed, device=spec.device, download=spec.download, amp=spec.amp,
                  precision=spec.precision, resume=True, command=list(spec.command))
    input_pass = spec.dataset.selection.pass_
    if cell.kind == "lp":
        return AttackJob(preset=None, preset_name=cell.label, settings=None,
                         pass_name=lp_pass_name(cell.label, input_pass),
                         lp=lp_settings(cell.label, steps=spec.lp_steps), **common)
    kwargs = {} if spec.steps is None else {"steps": spec.steps}
    config = cell.label if label_config(cell.label) is not None else None
    plan = plan_attack(config, None if config else cell.label, dict(spec.overrides),
                       compat=spec.compat, **kwargs)
    return AttackJob(preset=plan.preset, preset_name=plan.preset_name,
                     settings=replace(plan.settings, early_stop=spec.early_stop),
                     config_name=config, pass_name=attack_pass_name(plan.preset_name, input_pass),
                     **common)


def shard_cells(cells: list[Cell], shard: Optional[tuple[int, int]]) -> list[Cell]:
    """The cells of shard ``i`` of ``N``: every N-th cell, starting at ``i - 1``."""
    if shard is None:
        return list(cells)
    i, n = shard
    return list(cells)[i - 1::n]


def checkpoint_record(spec: BenchmarkSpec, name: str) -> dict:
    """What identifies a network's weights: its name, the checkpoint given and, for a file, its
    sha256; for a network from outside the package also its code (``source``)."""
    checkpoint = spec.checkpoints.get(name)
    record = {"network": name, "checkpoint": checkpoint, "sha256": None}
    if checkpoint is not None and Path(checkpoint).is_file():
        record["sha256"] = sha256_of(Path(checkpoint))
    source = spec.resolved[name].source()
    if source is not None:
        record["source"] = source        # a network of your own: its file and that file's sha256
    return record


def run_grid(spec: BenchmarkSpec, shard: Optional[tuple[int, int]] = None,
             execute: Callable[[AttackJob], dict] = run_attack,
             on_cell: Callable[[int, int, Cell], None] = lambda i, n, c: None) -> list[Cell]:
    """Run the cells of ``shard`` (all without one) through ``execute``; return them.

    Every cell's job is built before the first runs, and every network from outside the package
    is built and run once on the first pair (:func:`~weathergen.attack.probe_job_network`), so a
    bad preset, method, option or network fails before anything is written.
    """
    cells = shard_cells(spec.cells(), shard)
    jobs = [cell_job(spec, c) for c in cells]
    for job in jobs:
        job.precision_setting()             # a precision the network or device cannot run
    for job in {job.model: job for job in jobs if job.model.external}.values():
        refs = job.dataset.pairs()
        try:
            if refs:                        # none: run_attack says so
                probe_job_network(job, job_model(job), refs[0])
        except ConfigError as exc:
            raise renamed(exc, "networks") from None
    for i, (cell, job) in enumerate(zip(cells, jobs)):
        on_cell(i, len(cells), cell)
        execute(job)
    return cells
