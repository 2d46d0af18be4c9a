"""Robustness of a flow network to rendered weather: AEE(f, f̌) and EPE against ground truth.

For every pair of a folder written by ``weathergen render`` (or ``weathergen attack``), the network
runs on the clean frames (flow ``f``) and on the weather frames (flow ``f̌``). The paper's
robustness figure is ``AEE(f, f̌)``, the mean over pixels of ``‖f − f̌‖``, which needs no ground
truth; where the input dataset has ground-truth flow, the end-point errors of ``f`` and ``f̌``
against it are reported alongside. All figures are in pixels.

The clean frames come from the dataset recorded in the folder's manifest (``input``); the user may
point elsewhere (the same dataset stored at another path).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional

import torch

from .datasets import Dataset, reopen_dataset
from .errors import ConfigError, DatasetError, FormatError
from .flow import aee
from .framepair import PairId
from .io.atomic import atomic_write_bytes
from .io.exr import read_exr
from .io.images import read_image
from .outputs import MANIFEST, PairOutput, pair_identity, read_metadata


@dataclass
class WeatherFolder:
    """A render (or attack) output opened for reading.

    Attributes: root; pass_name (the folder of the weather frames); fmt (png, exr or both);
    input (the manifest's description of the clean dataset); pairs (complete pairs, sorted).
    """

    root: Path
    pass_name: str
    fmt: str
    input: dict
    pairs: list
    sequence: bool = False        # a `render --sequence` tree: scenes hold every frame

    @classmethod
    def open(cls, root: str | Path) -> "WeatherFolder":
        root = Path(root)
        manifest_path = root / MANIFEST
        if not manifest_path.is_file():
            raise ConfigError(f"{manifest_path}: not found; --weather takes the folder of a "
                              "`weathergen render` or `weathergen attack` run")
        try:
            manifest = json.loads(manifest_path.read_text())
            outputs, source = manifest["outputs"], manifest["input"]
            pass_name, fmt = outputs["pass"], outputs.get("format", "png")
            sequence = bool(outputs.get("sequence", False))
        except (ValueError, KeyError, TypeError):
            raise FormatError(manifest_path, "not a weathergen render or attack manifest") from None
        pairs = []
        for meta in sorted(root.glob("*/particles/*/frame_*.npz")):
            pid = pair_identity(read_metadata(meta))
            if PairOutput.of(root, pid, pass_name, fmt, sequence=sequence).is_complete():
                pairs.append(pid)
        if not pairs:
            raise DatasetError(f"{root}: holds no complete weather pairs")
        return cls(root, pass_name, fmt, source, sorted(pairs), sequence)

    def frames(self, pair_id: PairId) -> tuple[torch.Tensor, torch.Tensor]:
        """The weather frames of a pair. Shape: two (3, H, W) float32 in [0, 1]."""
        out = PairOutput.of(self.root, pair_id, self.pass_name, self.fmt, sequence=self.sequence)
        if self.fmt == "exr":
            images = [read_exr(p)["RGB"].clip(0, 1) for p in out.frames_exr]
        else:
            images = [read_image(p) for p in out.frames_png]
        return tuple(torch.from_numpy(img.copy()).permute(2, 0, 1).contiguous() for img in images)

    def clean_dataset(self, dataset: Optional[str] = None, root: Optional[str] = None,
                      pass_: Optional[str] = None) -> Dataset:
        """The dataset the weather was rendered into (as recorded), or the one given."""
        if dataset is None or dataset == self.input.get("dataset"):
            description = dict(self.input)        # with every recorded reader option
        else:                                     # another reader: its own defaults
            description = {"dataset": dataset, "split": self.input.get("split", "training")}
        if root is not None:
            description["root"] = root
        if pass_ is not None:
            description["pass"] = pass_
        return reopen_dataset(description)


@dataclass
class EvalRow:
    """One pair (pixels): AEE(f, f̌); EPE of f and f̌ against ground truth (None without it)."""

    pair: str
    aee_weather: float
    epe_clean: Optional[float] = None
    epe_weather: Optional[float] = None


def evaluate_frames(model, clean1: torch.Tensor, clean2: torch.Tensor, weather1: torch.Tensor,
                    weather2: torch.Tensor, gt: Optional[torch.Tensor] = None,
                    valid: Optional[torch.Tensor] = None, device="cpu"
                    ) -> tuple[float, Optional[float], Optional[float]]:
    """``(AEE(f, f̌), EPE(f, gt), EPE(f̌, gt))`` for one pair.

    Shape: frames (3, H, W) in [0, 1]; gt (2, H, W) pixels; valid (1, H, W) bool.
    """
    with torch.no_grad():
        batch1 = torch.stack((clean1, weather1)).to(device)
        batch2 = torch.stack((clean2, weather2)).to(device)
        flows = model(batch1, batch2).cpu()     # both pairs in one batch
    clean, weather = flows[:1], flows[1:]
    robustness = float(aee(weather, clean)[0])
    if gt is None:
        return robustness, None, None
    gt = gt[None].float()
    mask = None if valid is None else valid[None]
    return robustness, float(aee(clean, gt, mask)[0]), float(aee(weather, gt, mask)[0])


def run_evaluation(model, folder: WeatherFolder, dataset: Dataset, device="cpu",
                   on_pair: Callable[[EvalRow], None] = lambda r: None) -> tuple[list, dict]:
    """Evaluate every complete pair of ``folder``; return the rows and their means."""
    refs = {(r.id.split, r.id.scene, r.id.frame): r for r in dataset.pairs()}
    rows = []
    for pid in folder.pairs:
        ref = refs.get((pid.split, pid.scene, pid.frame))
        if ref is None:
            raise DatasetError(f"{dataset.root}: has no clean pair {pid.scene} frame {pid.frame} "
                               f"(split {pid.split}) for the weather pair in {folder.root}")
        pair = dataset.load(ref)
        weather1, weather2 = folder.frames(pid)
        if tuple(weather1.shape) != tuple(pair.image1.shape):
            raise DatasetError(f"{folder.root}: weather frames of {pid} are "
                               f"{tuple(weather1.shape)}, the clean ones {tuple(pair.image1.shape)}")
        a, e_clean, e_weather = evaluate_frames(model, pair.image1, pair.image2, weather1,
                                                weather2, pair.flow, pair.flow_valid, device)
        row = EvalRow(str(pid), a, e_clean, e_weather)
        rows.append(row)
        on_pair(row)
    return rows, mean_rows(rows)


def mean_rows(rows: list[EvalRow]) -> dict:
    """Means over pairs (EPE over the pairs that have ground truth)."""
    out: dict = {"pairs": len(rows)}
    for key in ("aee_weather", "epe_clean", "epe_weather"):
        values = [getattr(r, key) for r in rows if getattr(r, key) is not None]
        out[key] = sum(values) / len(values) if values else None
    return out


def write_evaluation(path: str | Path, info: dict, rows: list[EvalRow], summary: dict) -> Path:
    """Write the evaluation as JSON (``info``: model, weather folder, ...), atomically."""
    data = {**info, "summary": summary, "pairs": [asdict(r) for r in rows]}
    return atomic_write_bytes(path, json.dumps(data, indent=2, default=str).encode())
