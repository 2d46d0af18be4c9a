"""The on-disk layout of an attack output and its writers (extends :mod:`~weathergen.outputs.pairs`).

An attack folder is a render folder with more files, so that everything that reads a render
output reads it too (``weathergen render --particles OUT`` re-renders the adversarial particles,
``weathergen evaluate --weather OUT`` measures them, the Sintel reader reads ``--pass PASS``)::

    OUT/manifest.json                         preset_name, preset, input, outputs, attack settings,
                                              model, per-pair figures and the mean summary
    OUT/summary.json                          the mean summary alone (also printed as a table)
    OUT/SPLIT/PASS/PAIR/frame_FFFF.png        adversarial frames (best step, storage precision)
    OUT/SPLIT/depth|camdata_left|flow/PAIR/   geometry, as written by ``render``
    OUT/SPLIT/attack_flow/PAIR/benign.flo     flow on the clean frames
    OUT/SPLIT/attack_flow/PAIR/initial.flo    flow with the unoptimised (random) weather
    OUT/SPLIT/attack_flow/PAIR/adversarial.flo   flow with the adversarial weather
    OUT/SPLIT/attack_flow/PAIR/target.flo     the attack's target flow
    OUT/SPLIT/attack_flow/PAIR/*.png          colour-wheel pictures of the four, one shared scale
    OUT/SPLIT/attack_log/PAIR.csv             one row per step: loss, distance, penalty, ...
    OUT/SPLIT/particles/PAIR/frame_FFFF.npz   best particles in the render metadata format, plus
                                              ``attack_summary`` (JSON); written last

Every file is written atomically and the metadata file last: a pair whose metadata loads and whose
listed files exist is complete, and a resumed run starts at the next pair that is not.
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from ..datasets import NativeFlow
from ..errors import FormatError
from ..flow import flow_to_color
from ..framepair import FramePair, PairId
from ..io.atomic import atomic_write_bytes
from ..io.images import write_png
from ..io.sintel_formats import write_flo
from .metadata import read_metadata
from .pairs import PairOutput, write_pair_outputs

FLOW_KINDS = ("benign", "initial", "adversarial", "target")
LOG_COLUMNS = ("step", "loss", "distance", "penalty", "robustness", "best_distance", "seconds")


@dataclass(frozen=True)
class AttackPairOutput:
    """Where one attacked pair's files go: the render layout (``base``) plus flows and a log."""

    base: PairOutput

    @classmethod
    def of(cls, root, pair_id: PairId, pass_name: str,
           native: Optional[NativeFlow] = None) -> "AttackPairOutput":
        """``native``: the input's own form of flow (its reader's ``native_flow``)."""
        return cls(PairOutput.of(root, pair_id, pass_name, "png", geometry=True, native=native))

    @property
    def root(self) -> Path:
        return self.base.root

    def flow_file(self, kind: str, ext: str = "flo") -> Path:
        return self.root / self.base.split / "attack_flow" / self.base.pair_dir / f"{kind}.{ext}"

    @property
    def log(self) -> Path:
        return self.root / self.base.split / "attack_log" / f"{self.base.pair_dir}.csv"

    @property
    def metadata(self) -> Path:
        return self.base.metadata

    def is_complete(self) -> bool:
        return self.base.is_complete()


def encode_log(history) -> bytes:
    """CSV bytes of a list of :class:`~weathergen.attack.StepRecord` (one row per step)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(LOG_COLUMNS)
    for r in history:
        row = asdict(r)
        writer.writerow([row["step"]] + [f"{row[c]:.6g}" for c in LOG_COLUMNS[1:]])
    return buf.getvalue().encode()


def read_log(path: str | Path) -> list[dict]:
    """The rows of a per-step log as dicts of floats (``step`` as int)."""
    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "attack log not found")
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return [{k: (int(v) if k == "step" else float(v)) for k, v in r.items()} for r in rows]


def write_attack_pair(out: AttackPairOutput, pair: FramePair, frames: tuple[np.ndarray, np.ndarray],
                      opacity: tuple[np.ndarray, np.ndarray], metadata: dict[str, np.ndarray],
                      flows: dict[str, torch.Tensor], history, summary: dict) -> list[Path]:
    """Write one attacked pair: flows, colour wheels, log, then the render files, metadata last.

    Shape: frames (H, W, 3) float [0, 1]; opacity (H, W); flows ``{kind: (1, 2, H, W) or
    (2, H, W)}`` pixels for every kind of :data:`FLOW_KINDS`.
    """
    written = []
    fields = [flows[k].detach().cpu().float().reshape(2, *flows[k].shape[-2:]) for k in FLOW_KINDS]
    pictures = flow_to_color(fields)           # one shared scale across the comparison
    for kind, field_, picture in zip(FLOW_KINDS, fields, pictures):
        written.append(write_flo(out.flow_file(kind), field_.numpy().transpose(1, 2, 0)))
        written.append(write_png(out.flow_file(kind, "png"), picture.permute(1, 2, 0).numpy()))
    written.append(atomic_write_bytes(out.log, encode_log(history)))
    meta = dict(metadata)
    meta["attack_summary"] = np.array(json.dumps(summary, sort_keys=True))
    meta["attack_files"] = np.array(json.dumps([str(p.relative_to(out.root)) for p in written]))
    return written + write_pair_outputs(out.base, pair, frames, opacity, meta)


def read_pair_summary(out: AttackPairOutput) -> Optional[dict]:
    """The per-pair figures stored in a complete pair's metadata (None if it has none)."""
    arrays = read_metadata(out.metadata)
    if "attack_summary" not in arrays:
        return None
    return json.loads(str(arrays["attack_summary"]))
