"""``weathergen models``: the flow networks and their checkpoints, or one network in full."""

from __future__ import annotations

import click
from rich.console import Console
from rich.table import Table

from weathergen.errors import WeatherGenError
from weathergen.models import (ENTRY_POINT_GROUP, available_checkpoints, available_models, build_model,
                               cache_dir, checkpoint_spec, entry_points, model_spec, resolve_network)
from weathergen.models.checkpoints import cached_path, shipped_path

from .options import STOPPED, exit_codes


@click.command("models", epilog=exit_codes(("0", "listed or shown"),
                                            ("2", "an unknown network, or one that does not load "
                                                  "(one line)"),
                                            STOPPED))
@click.argument("name", required=False)
def models_command(name):
    """List the flow networks (those weathergen ships and those installed packages offer through
    the entry-point group weathergen.models) with their checkpoints, or show network NAME (a
    registered name, an installed network, FILE.py:NAME or package.module:NAME) in full."""
    console = Console(width=160)
    if name is not None:
        _show(console, name)
        return
    table = Table(title="flow networks (--model NAME; a checkpoint name selects its network)",
                  header_style="bold")
    for col in ("name", "default checkpoint", AVAILABLE, "mixed precision", "description"):
        table.add_column(col, no_wrap=col not in (AVAILABLE, "description"))
    for arch in available_models():
        spec = model_spec(arch)
        table.add_row(arch, spec.default_checkpoint or "–", _checkpoints(arch),
                      _amp(spec), spec.description)
    console.print(table)
    installed = entry_points()
    if installed:
        table = Table(title=f"installed networks (entry points of {ENTRY_POINT_GROUP})",
                      header_style="bold")
        for col in ("name", "entry point", "distribution", "status"):
            table.add_column(col)
        for ep_name, ep in sorted(installed.items()):
            dist = getattr(ep, "dist", None)
            table.add_row(ep_name, ep.value, f"{dist.metadata['Name']} {dist.version}" if dist else "–",
                          _status(ep_name))
        console.print(table)
    else:
        console.print(f"No installed package offers a network (entry-point group "
                      f"{ENTRY_POINT_GROUP}).", highlight=False)
    console.print(f"Checkpoint cache: {cache_dir()}. A network of your own: --model FILE.py:NAME "
                  f"or --model package.module:NAME (docs/models.md).", highlight=False,
                  soft_wrap=True)


#: The column of checkpoints, those at hand marked.
AVAILABLE = "checkpoints (* in the cache or shipped)"


def _local_file(name: str):
    """The file of checkpoint ``name`` here (the cache's, else the shipped one), or None."""
    spec = checkpoint_spec(name)
    return cached_path(spec) if cached_path(spec).is_file() else shipped_path(spec)


def _checkpoints(arch: str) -> str:
    return ", ".join(f"{c}{'*' if _local_file(c) else ''}" for c in available_checkpoints(arch)) or "–"


def _amp(spec) -> str:
    if not spec.mixed_precision:
        return "no"
    return "yes (on by default on CUDA)" if spec.amp else "yes"


def _status(ep_name: str) -> str:
    """``ok``, the registered name that shadows the entry point, or why it cannot be loaded."""
    if ep_name in available_models() or ep_name in available_checkpoints():
        return f"shadowed by the registered {ep_name!r}"
    try:
        resolve_network(ep_name)
    except WeatherGenError as exc:
        return f"error: {exc}"
    return "ok"


def _show(console: Console, name: str) -> None:
    """One network: its settings and checkpoints, or where its code comes from."""
    if name not in available_models() and name in available_checkpoints():
        name = checkpoint_spec(name).architecture       # a checkpoint shows its network
    spec = resolve_network(name)
    table = Table(title=f"flow network {name}", header_style="bold", show_header=False)
    table.add_column("key")
    table.add_column("value")
    record = spec.source()
    if record is not None:
        for key, value in record.items():
            if value is not None:
                table.add_row(key, str(value))
        model = build_model(spec)
        table.add_row("padding multiple, min size", f"{model.multiple}, {model.min_size}")
    else:
        spec = model_spec(spec.architecture)
        table.add_row("description", spec.description)
        table.add_row("default checkpoint", spec.default_checkpoint or "–")
    table.add_row("mixed precision", _amp(spec))
    console.print(table)
    if record is not None:
        return
    checkpoints = Table(title=f"checkpoints of {name}", header_style="bold")
    for col in ("name", "trained on", "file (cache or shipped)", "from", "licence"):
        checkpoints.add_column(col)
    for c in available_checkpoints(name):
        cspec = checkpoint_spec(c)
        path = _local_file(c)
        checkpoints.add_row(c, cspec.description, str(path) if path else "no",
                            cspec.url or cspec.page or "–", cspec.licence or "–")
    console.print(checkpoints)
