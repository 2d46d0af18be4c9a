"""Entry point: the ``weathergen`` click group and the error boundary of every command."""

from __future__ import annotations

import sys

import click

from weathergen import __version__
from weathergen.errors import WeatherGenError


class _Group(click.Group):
    """A click group that turns user errors into one line on stderr and exit code 2."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except WeatherGenError as exc:
            click.echo(f"Error: {exc}", err=True)
            sys.exit(2)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="weathergen")
def cli():
    """Physically placed weather for optical-flow datasets, and weather attacks on flow networks."""


def _register():
    from . import check, demo_scene, inspect_cmd, presets_cmd, render  # noqa: F401  (each module adds its command)


def main(argv=None):
    _register()
    return cli.main(args=argv, prog_name="weathergen")
