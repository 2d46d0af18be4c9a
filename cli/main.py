"""Entry point: the ``weathergen`` click group and the error boundary of every command."""

from __future__ import annotations

import sys

import click

from weathergen import __version__
from weathergen.errors import WeatherGenError


#: Where the group keeps the command line it was given (``ctx.meta``), for manifests.
ARGV_KEY = "weathergen.argv"


#: Library parameters whose command-line option has another name; the others are ``--name``.
OPTIONS = {"particles_from": "--particles", "config_name": "--config", "fmt": "--format",
           "overrides": "--set"}


def option_of(parameter: str) -> str:
    """The command-line option of a library parameter (``pass_name`` -> ``--pass-name``)."""
    return OPTIONS.get(parameter, "--" + parameter.replace("_", "-"))


class _Group(click.Group):
    """A click group that turns user errors into one line on stderr and exit code 2."""

    def parse_args(self, ctx, args):
        ctx.meta[ARGV_KEY] = ["weathergen", *args]
        return super().parse_args(ctx, args)

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except WeatherGenError as exc:
            click.echo(f"Error: {exc.render(option_of)}", err=True)
            sys.exit(2)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="weathergen")
def cli():
    """Physically placed weather for optical-flow datasets, and weather attacks on flow networks."""


def _register():
    # Each module adds its command to the group on import.
    from . import (attack, check, demo_scene, evaluate, inspect_cmd,  # noqa: F401
                   presets_cmd, render)


def main(argv=None):
    _register()
    return cli.main(args=argv, prog_name="weathergen")
