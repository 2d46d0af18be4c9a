"""Dependency floors: setup.cfg's lower bounds are the versions constraints/oldest.txt tests, and
the OpenCV logging control works on every allowed OpenCV (some wheels lack cv2.utils.logging)."""

from __future__ import annotations

import configparser
import re
import types
from pathlib import Path

import pytest

import weathergen.io.images as images

REPO = Path(__file__).resolve().parents[1]


def floors() -> dict[str, str]:
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    out = {}
    for line in cfg["options"]["install_requires"].split("\n"):
        m = re.match(r"^\s*([A-Za-z0-9_.-]+)>=([0-9.]+)\s*$", line)
        if m:
            out[m.group(1).lower()] = m.group(2)
    return out


def pins() -> dict[str, str]:
    out = {}
    for line in (REPO / "constraints" / "oldest.txt").read_text().splitlines():
        m = re.match(r"^([A-Za-z0-9_.-]+)==([0-9.]+)$", line.strip())
        if m:
            out[m.group(1).lower()] = m.group(2)
    return out


@pytest.mark.skipif(not (REPO / "setup.cfg").exists(), reason="runs from a source checkout")
def test_every_floor_is_a_tested_version():
    declared, tested = floors(), pins()
    assert set(declared) - {"torch"} <= set(tested), "a dependency without a tested lowest version"
    for name, floor in declared.items():
        if name == "torch":
            continue          # installed through the Makefile's TORCH pin, see constraints/oldest.txt
        # the floor names the tested version (or a prefix of it: 'rich>=13' and rich 13.0.0)
        version = tested[name].split(".")
        assert floor.split(".") == version[: len(floor.split("."))], (name, floor, tested[name])


def test_quieting_opencv_without_cv2_utils_logging(monkeypatch):
    calls = []
    # opencv-contrib-python-headless 4.8 / 4.11: cv2.utils exists, its logging does not
    monkeypatch.setattr(images, "cv2", types.SimpleNamespace(utils=types.SimpleNamespace(),
                                                             setLogLevel=calls.append))
    images.quiet_opencv()
    assert calls == [2]                                     # OpenCV's LOG_LEVEL_ERROR
    # a wheel with neither: nothing to do, and no crash
    monkeypatch.setattr(images, "cv2", types.SimpleNamespace())
    images.quiet_opencv()
    # the full logging module
    logging = types.SimpleNamespace(LOG_LEVEL_ERROR=2, setLogLevel=calls.append)
    monkeypatch.setattr(images, "cv2", types.SimpleNamespace(utils=types.SimpleNamespace(logging=logging)))
    images.quiet_opencv()
    assert calls == [2, 2]
