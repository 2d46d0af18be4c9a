"""The manifest of an output folder: written by the runs, merged from shard parts, read back.

``OUT/manifest.json`` records a run: the resolved preset, the seed, the input dataset
(:meth:`~weathergen.datasets.Dataset.describe`), the output settings (``outputs``: pass, format,
geometry), every run and every pair. A render writes one part per shard below
``OUT/manifest.d/`` and merges them after every run; an attack writes the manifest itself after
every pair. Render and attack manifests share the top-level entries ``preset_name``, ``preset``,
``seed``, ``input`` and ``outputs``, so every reader of an output folder reads both, through
:func:`read_manifest`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from .. import __version__
from ..errors import ConfigError, FormatError
from ..io.atomic import atomic_write_bytes

MANIFEST = "manifest.json"
MANIFEST_PARTS = "manifest.d"
#: The settings a render folder was started with; every later run and shard must agree with it.
RUN_CONFIG = ".config.json"
SUMMARY = "summary.json"
RENDER_FORMAT = "weathergen-render"
ATTACK_FORMAT = "weathergen-attack"
STATUSES = ("written", "skipped", "failed")


def jsonable(obj):
    """``obj`` as it reads back from JSON (tuples as lists, paths and other objects as text)."""
    return json.loads(json.dumps(obj, sort_keys=True, default=str))


# -- reading ----------------------------------------------------------------------------------

#: Who reads a manifest back, what that reader needs from it, and how the problems are said.
#: ``${name}`` names the parameter that pointed at the folder (see :mod:`weathergen.errors`).
_READERS = {
    "particles_from": (("preset_name", "preset"),
                       "${particles_from} takes the folder of an earlier render",
                       "not a weathergen render manifest"),
    "weather": (("input", "outputs.pass"),
                "${weather} takes the folder of a `weathergen render` or `weathergen attack` run",
                "not a weathergen render or attack manifest"),
    "preview": (("input", "outputs.pass", "outputs.format", "outputs.geometry"),
                "preview takes the folder of a render output",
                "not a weathergen render manifest"),
}


@dataclass(frozen=True)
class OutputManifest:
    """The manifest of a render or attack output, read back. ``data`` holds every entry."""

    path: Path
    data: dict

    @property
    def folder(self) -> Path:
        return self.path.parent

    @property
    def preset_name(self) -> str:
        return self.data["preset_name"]

    @property
    def preset(self) -> Optional[dict]:
        """The resolved preset (every key, plus ``name`` and ``source``); None for an Lp attack,
        which has no particles."""
        return self.data["preset"]

    @property
    def holds_particles(self) -> bool:
        """Whether the output's pairs store weather particles (an Lp attack's perturb the frames
        themselves and store none)."""
        return self.data.get("preset") is not None

    @property
    def input(self) -> dict:
        """The input dataset as :meth:`~weathergen.datasets.Dataset.describe` recorded it."""
        return self.data["input"]

    @property
    def pass_name(self) -> str:
        return self.data["outputs"]["pass"]

    @property
    def fmt(self) -> str:
        return self.data["outputs"].get("format", "png")

    @property
    def geometry(self) -> bool:
        return self.data["outputs"].get("geometry", True)

    @property
    def sequence(self) -> bool:
        """True for a ``render --sequence`` output: scenes hold every frame, not one pair each."""
        return bool(self.data.get("outputs", {}).get("sequence", False))


def read_manifest(folder: str | Path, reader: str) -> OutputManifest:
    """The manifest of an output folder, checked for what ``reader`` needs.

    ``reader`` is one of ``"particles_from"`` (stored particles are re-rendered or attacked),
    ``"weather"`` (the weather frames are evaluated) and ``"preview"``. A missing manifest raises
    ConfigError (the folder is not an output), an unreadable one FormatError; both name the file.
    """
    needs, takes, problem = _READERS[reader]
    path = Path(folder) / MANIFEST
    if not path.is_file():
        raise ConfigError(f"{path}: not found; {takes}")
    try:
        data = json.loads(path.read_text())
        for entry in needs:
            value = data
            for key in entry.split("."):
                value = value[key]
    except (OSError, ValueError, KeyError, TypeError):
        raise FormatError(path, problem) from None
    return OutputManifest(path, data)


def read_run_config(out: Path) -> Optional[dict]:
    """The settings a render folder was started with (None for a new folder or a lost file)."""
    path = Path(out) / MANIFEST_PARTS / RUN_CONFIG
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except ValueError:
        return None


def write_run_config(out: Path, config: dict) -> Path:
    (Path(out) / MANIFEST_PARTS).mkdir(exist_ok=True)
    return atomic_write_bytes(Path(out) / MANIFEST_PARTS / RUN_CONFIG,
                              json.dumps(jsonable(config), indent=2, sort_keys=True).encode())


# -- render manifests: one part per shard, merged ---------------------------------------------

def shard_part(out: Path, shard: tuple[int, int]) -> Path:
    """The manifest part of shard ``(i, n)``."""
    i, n = shard
    return Path(out) / MANIFEST_PARTS / f"shard-{i}-of-{n}.json"


def write_manifest_part(out: Path, shard: tuple[int, int], run: dict, pairs: dict[str, dict]) -> Path:
    """Record one run of a shard (``run``) and its pairs (key -> entry with a ``status``) in the
    shard's part, merging with the part's earlier runs: a pair skipped now keeps the entry of the
    run that wrote it."""
    path = shard_part(out, shard)
    part = {"runs": [], "pairs": {}}
    if path.exists():
        try:
            part = json.loads(path.read_text())
        except ValueError:
            pass
    part["runs"].append(run)
    for key, entry in pairs.items():
        if entry["status"] == "skipped" and key in part["pairs"]:
            continue        # keep the timings of the run that wrote it
        part["pairs"][key] = entry
    atomic_write_bytes(path, json.dumps(part, indent=2, sort_keys=True).encode())
    return path


def merge_manifest(out: Path) -> Path:
    """Merge every shard part into ``manifest.json`` (idempotent; run after every run)."""
    out = Path(out)
    config = read_run_config(out) or {}
    runs, pairs, shards = [], {}, []
    for part_path in sorted((out / MANIFEST_PARTS).glob("shard-*.json")):
        try:
            part = json.loads(part_path.read_text())
        except ValueError:
            raise FormatError(part_path, "manifest part is not valid JSON; rerun that shard with "
                                         "${resume} to rewrite it") from None
        shards.append(part_path.stem)
        runs += part.get("runs", [])
        pairs.update(part.get("pairs", {}))
    manifest = {
        "format": RENDER_FORMAT,
        "format_version": 1,
        "weathergen_version": __version__,
        **config,
        "shards": shards,
        "runs": runs,
        "pairs": dict(sorted(pairs.items())),
        "summary": {s: sum(p["status"] == s for p in pairs.values()) for s in STATUSES},
    }
    return atomic_write_bytes(out / MANIFEST, json.dumps(manifest, indent=2).encode())


# -- attack manifests ---------------------------------------------------------------------------

def read_attack_manifest(out: Path) -> dict:
    """The manifest of an attack folder, as written by :func:`write_attack_manifest`."""
    path = Path(out) / MANIFEST
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        raise FormatError(path, "not a readable attack manifest") from None


def read_summary(out: Path) -> Optional[dict]:
    """The mean figures of an attack folder (``summary.json``), None where the run has written
    none yet; an unreadable file raises FormatError naming it."""
    path = Path(out) / SUMMARY
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        raise FormatError(path, "not a readable attack summary") from None


def write_attack_manifest(out: Path, config: dict, pairs: dict, summary: dict, runs: list) -> Path:
    """Write ``manifest.json`` (and ``summary.json``) atomically.

    Top-level ``preset_name``, ``preset``, ``input`` and ``outputs`` mirror a render manifest, so
    ``render --particles`` and ``evaluate --weather`` accept the folder.
    """
    manifest = {
        "format": ATTACK_FORMAT, "format_version": 1, "weathergen_version": __version__,
        "preset_name": config["preset_name"], "preset": config["preset"],
        "seed": config["seed"], "input": config["input"], "outputs": config["outputs"],
        "config": config, "runs": runs, "pairs": dict(sorted(pairs.items())), "summary": summary,
    }
    text = json.dumps(manifest, indent=2, default=str)
    atomic_write_bytes(Path(out) / SUMMARY, json.dumps(summary, indent=2).encode())
    return atomic_write_bytes(Path(out) / MANIFEST, text.encode())
