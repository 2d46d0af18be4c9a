"""A bar chart of AEE(f, f̌) per network and preset, drawn with OpenCV and numpy.

One group of bars per preset (the weather cells that name a preset, in the grid's order); in each
group one pair of bars per network, in the network's colour: the random weather (light) and the
adversarial weather (dark) side by side, as in the "weatherattacks" table. An unfinished cell has
no bar. The y axis starts at 0 px.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np

from ..io.images import write_png
from .grid import label_config, network_name

#: Network colours (RGB), in the order of the networks.
PALETTE = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
           (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207))
BAR, PAIR_GAP, NET_GAP, GROUP_GAP = 14, 2, 8, 36
LEFT, RIGHT, TOP, BOTTOM, PLOT_H = 64, 24, 78, 56, 300
FONT = cv2.FONT_HERSHEY_SIMPLEX
INK, GRID = (30, 30, 30), (225, 225, 225)
TITLE = "AEE(f, f_weather) [px] per network and preset: light = random, dark = adversarial"


def _text(img, text: str, org, scale=0.45, colour=INK, centre=False) -> None:
    text = "".join(c if ord(c) < 128 else "?" for c in text)    # Hershey fonts are ASCII
    if centre:
        (w, _), _ = cv2.getTextSize(text, FONT, scale, 1)
        org = (int(org[0] - w / 2), int(org[1]))
    cv2.putText(img, text, (int(org[0]), int(org[1])), FONT, scale, colour, 1, cv2.LINE_AA)


def _nice_step(top: float, ticks: int = 5) -> float:
    raw = max(top, 1e-9) / ticks
    power = 10 ** math.floor(math.log10(raw))
    return next(m * power for m in (1, 2, 2.5, 5, 10) if m * power >= raw)


def _light(colour, amount=0.55):
    return tuple(int(round(c + (255 - c) * amount)) for c in colour)


def draw_chart(values: dict, presets: Sequence[str], networks: Sequence[str]) -> np.ndarray:
    """The chart as an RGB image. ``values[(preset, network)] = (random, adversarial)``, either
    None where unknown. Shape: returns (H, W, 3) uint8."""
    n = max(1, len(networks))
    group_w = n * (2 * BAR + PAIR_GAP) + (n - 1) * NET_GAP
    groups = max(1, len(presets))
    (title_w, _), _ = cv2.getTextSize(TITLE, FONT, 0.45, 1)
    width = max(LEFT + title_w + RIGHT, LEFT + groups * group_w + (groups - 1) * GROUP_GAP + RIGHT)
    height = TOP + PLOT_H + BOTTOM
    img = np.full((height, width, 3), 255, dtype=np.uint8)
    known = [v for pair in values.values() for v in pair if v is not None]
    step = _nice_step(max(known, default=1.0) * 1.05)
    top = step * max(1, math.ceil(max(known, default=1.0) * 1.05 / step))
    base = TOP + PLOT_H

    def y_of(v: float) -> int:
        return int(round(base - PLOT_H * v / top))

    for i in range(int(round(top / step)) + 1):
        y = y_of(i * step)
        cv2.line(img, (LEFT, y), (width - RIGHT, y), GRID, 1)
        _text(img, f"{i * step:g}", (LEFT - 8 - 7 * len(f"{i * step:g}"), y + 4), 0.4)
    _text(img, TITLE, (LEFT, 20), 0.45)
    x = LEFT
    for j, net in enumerate(map(network_name, networks)):   # the legend
        colour = PALETTE[j % len(PALETTE)]
        if x + 16 + 8 * len(net) > width - RIGHT:
            break
        cv2.rectangle(img, (x, 34), (x + 10, 44), _light(colour), -1)
        cv2.rectangle(img, (x + 11, 34), (x + 21, 44), colour, -1)
        _text(img, net, (x + 26, 44), 0.42)
        x += 26 + 9 * len(net) + 16
    for g, preset in enumerate(presets):
        x0 = LEFT + g * (group_w + GROUP_GAP)
        for j, net in enumerate(networks):
            colour = PALETTE[j % len(PALETTE)]
            xb = x0 + j * (2 * BAR + PAIR_GAP + NET_GAP)
            for k, (v, fill) in enumerate(zip(values.get((preset, net), (None, None)),
                                              (_light(colour), colour))):
                if v is None:
                    continue
                left = xb + k * (BAR + PAIR_GAP)
                cv2.rectangle(img, (left, y_of(v)), (left + BAR - 1, base), fill, -1)
        _text(img, preset, (x0 + group_w / 2, base + 20), 0.45, centre=True)
    cv2.line(img, (LEFT, base), (width - RIGHT, base), INK, 1)
    cv2.line(img, (LEFT, TOP - 6), (LEFT, base), INK, 1)
    if not presets:
        _text(img, "no weather runs in the grid", (width / 2, TOP + PLOT_H / 2), 0.5, centre=True)
    return img


def draw_aee(path: str | Path, rows: list[dict], networks: Sequence[str]) -> Path:
    """Draw the chart of the grid's result ``rows`` (:func:`~.tables.collect_results`) and write
    it as a PNG, atomically."""
    presets = [r["label"] for r in rows if r["kind"] == "weather" and r["network"] == networks[0]
               and label_config(r["label"]) is None]
    values: dict[tuple[str, str], tuple[Optional[float], Optional[float]]] = {
        (r["label"], r["network"]): (r["aee_random"], r["aee_adversarial"])
        for r in rows if r["kind"] == "weather"}
    return write_png(path, draw_chart(values, presets, list(networks)))
