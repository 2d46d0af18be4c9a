"""A bar chart of AEE(f, f̌) per network and preset, and the severity ladders' curves, drawn with
OpenCV and numpy.

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


def _y_axis(img, known: list, x0: int, x1: int, base: int, height: int, scale: float):
    """Draw the grid lines from 0 up to a round ceiling above the ``known`` values (about five
    steps of 1, 2, 2.5 or 5 times a power of ten), labelled with their values, between ``x0`` and
    ``x1`` over ``height`` pixels above ``base``; return the value -> y mapping."""
    raw = max(max(known, default=1.0) * 1.05, 1e-9) / 5
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 2.5, 5, 10) if m * power >= raw)
    ceiling = step * max(1, math.ceil(max(known, default=1.0) * 1.05 / step))

    def y_of(v: float) -> int:
        return int(round(base - height * v / ceiling))

    for i in range(int(round(ceiling / step)) + 1):
        y = y_of(i * step)
        cv2.line(img, (x0, y), (x1, y), GRID, 1)
        _text(img, f"{i * step:g}", (x0 - 8 - 7 * len(f"{i * step:g}"), y + 4), scale)
    return y_of


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
    base = TOP + PLOT_H
    y_of = _y_axis(img, known, LEFT, width - RIGHT, base, PLOT_H, 0.4)
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


def draw_aee(path: str | Path, rows: list[dict], networks: Sequence[str],
             presets: Optional[Sequence[str]] = None) -> Path:
    """Draw the chart of the grid's result ``rows`` (:func:`~.tables.collect_results`) and write
    it as a PNG, atomically. ``presets``: the groups, in order (default: every weather cell that
    names a preset)."""
    if presets is None:
        presets = [r["label"] for r in rows if r["kind"] == "weather"
                   and r["network"] == networks[0] and label_config(r["label"]) is None]
    values: dict[tuple[str, str], tuple[Optional[float], Optional[float]]] = {
        (r["label"], r["network"]): (r["aee_random"], r["aee_adversarial"])
        for r in rows if r["kind"] == "weather"}
    return write_png(path, draw_chart(values, list(presets), list(networks)))


# -- severity ladders ----------------------------------------------------------------------------

PANEL_W, PANEL_H, PANEL_GAP = 300, 200, 70
LADDER_TITLE = ("Severity ladders per network: AEE(f, f_weather) and EPE [px] over the rungs; "
                "solid = adversarial, thin = random")


def draw_ladder_chart(curves: Sequence, networks: Sequence[str]) -> np.ndarray:
    """The curves of :func:`~.ladder.ladder_curves` as an RGB image: one row of two panels per
    ladder (AEE(f, f̌), then EPE against the ground truth), the points clean, light, moderate,
    heavy on the x axis, one colour per network (in the order of ``networks``), adversarial
    weather solid and thick, random weather thin and light. Shape: returns (H, W, 3) uint8."""
    ladders = list(dict.fromkeys(c.ladder for c in curves))
    colour = {net: PALETTE[j % len(PALETTE)] for j, net in enumerate(networks)}
    (title_w, _), _ = cv2.getTextSize(LADDER_TITLE, FONT, 0.45, 1)
    width = max(LEFT + 2 * PANEL_W + PANEL_GAP + RIGHT, LEFT + title_w + RIGHT)
    height = TOP + max(1, len(ladders)) * (PANEL_H + BOTTOM + 24)
    img = np.full((height, width, 3), 255, dtype=np.uint8)
    _text(img, LADDER_TITLE, (LEFT, 20), 0.45)
    x = LEFT
    for net in networks:                                          # the legend
        name = network_name(net)
        if x + 16 + 8 * len(name) > width - RIGHT:
            break
        cv2.line(img, (x, 40), (x + 20, 40), colour[net], 3, cv2.LINE_AA)
        _text(img, name, (x + 26, 44), 0.42)
        x += 26 + 9 * len(name) + 16
    for row, ladder in enumerate(ladders):
        top = TOP + row * (PANEL_H + BOTTOM + 24) + 20
        mine = [c for c in curves if c.ladder == ladder]
        for col, (index, label) in enumerate(((1, "AEE(f, f_weather)"), (2, "EPE vs ground truth"))):
            left = LEFT + col * (PANEL_W + PANEL_GAP)
            _panel(img, mine, colour, index, (left, top), f"{ladder}: {label}")
    if not ladders:
        _text(img, "no ladder in the grid", (width / 2, TOP + PANEL_H / 2), 0.5, centre=True)
    return img


def _panel(img, curves, colour, index: int, origin, title: str) -> None:
    """One panel: value ``index`` of each curve's points (1 AEE, 2 EPE) against the points."""
    left, top = origin
    base = top + PANEL_H
    known = [p[index] for c in curves for p in c.points if p[index] is not None]
    labels = [p[0].rsplit("-", 1)[-1] for p in curves[0].points] if curves else []
    xs = [left + 20 + i * (PANEL_W - 40) / max(1, len(labels) - 1) for i in range(len(labels))]
    y_of = _y_axis(img, known, left, left + PANEL_W, base, PANEL_H, 0.38)
    _text(img, title, (left, top - 6), 0.42)
    for x, label in zip(xs, labels):
        _text(img, label, (x, base + 18), 0.4, centre=True)
    for curve in sorted(curves, key=lambda c: c.mode != "random"):     # adversarial on top
        adversarial = curve.mode == "adversarial"
        tone = colour[curve.network] if adversarial else _light(colour[curve.network])
        points = [(int(round(x)), y_of(p[index])) for x, p in zip(xs, curve.points)
                  if p[index] is not None]
        for a, b in zip(points, points[1:]):
            cv2.line(img, a, b, tone, 2 if adversarial else 1, cv2.LINE_AA)
        for p in points:
            cv2.circle(img, p, 3 if adversarial else 2, tone, -1, cv2.LINE_AA)
    cv2.line(img, (left, base), (left + PANEL_W, base), INK, 1)
    cv2.line(img, (left, top), (left, base), INK, 1)


def draw_ladder(path: str | Path, curves: Sequence, networks: Sequence[str]) -> Path:
    """Draw :func:`draw_ladder_chart` and write it as a PNG, atomically."""
    return write_png(path, draw_ladder_chart(curves, list(networks)))
