"""Robustness of a flow network to rendered weather: AEE(f, f̌) and EPE against ground truth.

For every pair of a folder written by ``weathergen render`` (or ``weathergen attack``), the network
runs on the clean frames (flow ``f``) and on the weather frames (flow ``f̌``). The paper's
robustness figure is ``AEE(f, f̌)``, the mean over pixels of ``‖f − f̌‖``, which needs no ground
truth; where the input dataset has ground-truth flow, the end-point errors of ``f`` and ``f̌``
against it are reported alongside. The figures by region (the pixels the weather covers, found by
rendering the folder's particles again, and the rest) and KITTI's outlier rates of ``f̌`` are
those of :mod:`weathergen.attack.figures`. All figures are in pixels (rates in percent).

The clean frames come from the dataset recorded in the folder's manifest (``input``); the user may
point elsewhere (the same dataset stored at another path). The folder is read through
:class:`~weathergen.outputs.WeatherFolder`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional

import torch

from ..datasets import Dataset
from ..engine import render_pair
from ..errors import DatasetError
from ..flow import aee, weather_mask
from ..io.atomic import atomic_write_bytes
from ..models.external import check_finite
from ..outputs.reading import WeatherFolder
from .figures import FIGURE_KEYS, RegionFigures, mean_figures, region_figures


@dataclass
class EvalRow(RegionFigures):
    """One pair (pixels): AEE(f, f̌); EPE of f and f̌ against ground truth (None without it);
    the figures by region and outlier rates of f̌ (:class:`~weathergen.attack.figures.RegionFigures`)."""

    pair: str
    aee_weather: float
    epe_clean: Optional[float] = None
    epe_weather: Optional[float] = None


def frame_flows(model, clean1: torch.Tensor, clean2: torch.Tensor, weather1: torch.Tensor,
                weather2: torch.Tensor, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """The network's flow on the clean and on the weather frames, in one batch.
    Shape: frames (3, H, W) in [0, 1]; returns two (1, 2, H, W) on the CPU."""
    with torch.no_grad():
        batch1 = torch.stack((clean1, weather1)).to(device)
        batch2 = torch.stack((clean2, weather2)).to(device)
        flows = model(batch1, batch2).cpu()
    check_finite(flows, getattr(model, "architecture", "") or type(model).__name__, tuple(batch1.shape))
    return flows[:1], flows[1:]


def run_evaluation(model, folder: WeatherFolder, dataset: Dataset, device="cpu",
                   on_pair: Callable[[EvalRow], None] = lambda r: None) -> tuple[list, dict]:
    """Evaluate every complete pair of ``folder``; return the rows and their means.

    The network pads frames as the clean dataset's benchmark protocol does (``dataset.padding``).
    """
    model.padding = getattr(dataset, "padding", "even")
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
        clean, weather = frame_flows(model, pair.image1, pair.image2, weather1, weather2, device)
        a, e_clean, e_weather = _figures(clean, weather, pair.flow, pair.flow_valid)
        covered = weather_region(folder, pid, pair, device)
        row = EvalRow(str(pid), a, e_clean, e_weather,
                      **region_figures(clean, weather, covered, pair.flow, pair.flow_valid))
        rows.append(row)
        on_pair(row)
    return rows, mean_rows(rows)


def weather_region(folder: WeatherFolder, pair_id, pair, device="cpu") -> Optional[torch.Tensor]:
    """The pixels the folder's weather covers in a pair (opacity of its particles, rendered again
    into the clean pair at the plain β, above the threshold in either frame), or None where the
    folder holds no particles (an Lp attack). Shape: (H, W) bool."""
    particles = folder.particles(pair_id)
    if particles is None:
        return None
    with torch.no_grad():
        out = render_pair(pair, particles, device=device)
    return weather_mask(out.opacity1, out.opacity2)[0, 0].cpu()


def _figures(clean, weather, gt, valid) -> tuple[float, Optional[float], Optional[float]]:
    robustness = float(aee(weather, clean)[0])
    if gt is None:
        return robustness, None, None
    gt = gt[None].float()
    mask = None if valid is None else valid[None]
    return robustness, float(aee(clean, gt, mask)[0]), float(aee(weather, gt, mask)[0])


def mean_rows(rows: list[EvalRow]) -> dict:
    """Means over pairs (EPE over the pairs that have ground truth; the figures by region and
    outlier rates as :func:`~weathergen.attack.figures.mean_figures`)."""
    out: dict = {"pairs": len(rows)}
    for key in ("aee_weather", "epe_clean", "epe_weather"):
        values = [getattr(r, key) for r in rows if getattr(r, key) is not None]
        out[key] = sum(values) / len(values) if values else None
    out.update(mean_figures([{k: getattr(r, k) for k in (*FIGURE_KEYS, "gt_valid_px")}
                             for r in rows]))
    return out


def default_evaluation_path(weather: str | Path, model: str, published: bool = False) -> Path:
    """Where the figures go when no file is given: ``WEATHER/evaluate-<model>.json`` beside a
    weathergen output; for a published set of the paper's weather (someone else's data, left as
    it is) ``evaluate-<set>-<model>.json`` in the working folder."""
    if published:
        return Path(f"evaluate-{Path(weather).resolve().name}-{model}.json")
    return Path(weather) / f"evaluate-{model}.json"


def write_evaluation(path: str | Path, info: dict, rows: list[EvalRow], summary: dict) -> Path:
    """Write the evaluation as JSON (``info``: model, weather folder, ...), atomically."""
    data = {**info, "summary": summary, "pairs": [asdict(r) for r in rows]}
    return atomic_write_bytes(path, json.dumps(data, indent=2, default=str).encode())
