"""The settings behind a set of figures, as every table, JSON and CSV of ``evaluate``, ``attack``
and ``benchmark`` carries them, so that two scores can be compared (or known not to be).

:func:`run_settings` writes the one record: the network, its checkpoint and the checkpoint's
sha256, the refinement iterations, the precision the network ran in, the padding of its input,
the crop (weathergen evaluates and attacks whole frames: ``none``), the attack's steps and
learning rates (None for an evaluation) and the seed of the weather. :func:`settings_text` is
the record in one line, for the tables that have no room for a column each.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Mapping, Optional

from ..models import Network, resolve_network
from ..models.checkpoints import sha256_of
from ..models.registry import available_checkpoints, checkpoint_spec

#: The keys of the record, in order.
SETTINGS_KEYS = ("network", "checkpoint", "checkpoint_sha256", "iters", "precision", "padding",
                 "crop", "steps", "learning_rates", "seed")


def run_settings(network: Network | str, checkpoint=None, *, iters: Optional[int] = None,
                 precision: str = "float32", padding: Optional[str] = None, steps: Optional[int] = None,
                 learning_rates: Optional[Mapping[str, float]] = None,
                 seed: Optional[int] = None) -> dict:
    """The settings record (keys :data:`SETTINGS_KEYS`). ``iters``: as the network ran them (None:
    its own default); ``precision``: the network's arithmetic (:data:`~weathergen.models.PRECISIONS`);
    ``padding``: where padding rows go (the dataset's protocol, ``even`` or ``bottom``)."""
    network = network if isinstance(network, Network) else resolve_network(network)
    return {"network": network.name,
            "checkpoint": None if checkpoint is None else str(checkpoint),
            "checkpoint_sha256": checkpoint_sha256(network, checkpoint),
            "iters": iters, "precision": precision, "padding": padding,
            "crop": "none", "steps": steps,
            "learning_rates": dict(learning_rates) if learning_rates else None, "seed": seed}


def checkpoint_sha256(network: Network, checkpoint=None) -> Optional[str]:
    """The sha256 of the weights: of the file given, else the one registered for the named
    checkpoint (the network's default where none is given); None where neither is known."""
    if checkpoint is not None and Path(checkpoint).is_file():
        path = Path(checkpoint).resolve()
        stat = path.stat()
        return _file_sha256(str(path), stat.st_mtime_ns, stat.st_size)
    if checkpoint is None:
        checkpoint = network.name if network.name in available_checkpoints() else network.default_checkpoint
    if checkpoint is not None and str(checkpoint) in available_checkpoints():
        return checkpoint_spec(str(checkpoint)).sha256
    return None


@lru_cache(maxsize=16)
def _file_sha256(path: str, mtime_ns: int, size: int) -> str:
    return sha256_of(Path(path))


def settings_text(settings: Mapping) -> str:
    """The record in one line: ``network raft (checkpoint raft-sintel, sha256 0123456789ab),
    iters 12, float32, padding even, crop none, 20 steps, lr 0.001, seed 0`` (the unset left
    out)."""
    weights = ", ".join(part for part in (
        settings.get("checkpoint") and f"checkpoint {settings['checkpoint']}",
        settings.get("checkpoint_sha256") and f"sha256 {settings['checkpoint_sha256'][:12]}")
        if part)
    rates = settings.get("learning_rates") or {}
    parts = [f"network {settings.get('network')}" + (f" ({weights})" if weights else ""),
             f"iters {settings['iters']}" if settings.get("iters") is not None else
             "iters: the network's default", settings.get("precision"),
             f"padding {settings.get('padding')}", f"crop {settings.get('crop')}",
             f"{settings['steps']} steps" if settings.get("steps") is not None else None,
             ", ".join(f"{k} {v:g}" for k, v in rates.items()) or None,
             f"seed {settings['seed']}" if settings.get("seed") is not None else None]
    return ", ".join(p for p in parts if p)
