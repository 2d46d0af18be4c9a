"""Entry point: the ``weathergen`` click group and the error boundary of every command."""

from __future__ import annotations

from . import startup  # first: Ctrl-C while the commands import torch is one line

import signal
import sys

import click

from weathergen import __version__
from weathergen.errors import WeatherGenError

from .attack import attack
from .benchmark import benchmark
from .check import check
from .demo_scene import demo_scene
from .evaluate import evaluate
from .inspect_cmd import inspect, preview
from .models_cmd import models_command
from .options import ARGV_KEY, exit_codes, option_of
from .presets_cmd import presets_command
from .render import render
from .stopping import terminate_as_interrupt

startup.started()


class _Group(click.Group):
    """A click group that turns user errors into one line on stderr and exit code 2."""

    def parse_args(self, ctx, args):
        ctx.meta[ARGV_KEY] = ["weathergen", *args]
        return super().parse_args(ctx, args)

    def invoke(self, ctx):
        stopped_by: list = []
        try:
            with terminate_as_interrupt() as stopped_by:
                return super().invoke(ctx)
        except WeatherGenError as exc:
            click.echo(f"Error: {exc.render(option_of)}", err=True)
            sys.exit(2)
        except KeyboardInterrupt:
            # the commands that run jobs say how far they got themselves; any other is stopped
            # before it wrote anything under a final name (every write is atomic)
            signum = stopped_by[0] if stopped_by else signal.SIGINT
            click.echo(f"Interrupted ({signal.Signals(signum).name}); no file was left "
                       "half-written.", err=True)
            sys.exit(128 + signum)


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]},
             epilog=exit_codes(
                 ("0", "done"), ("1", "done, but some pairs failed or were left out (named)"),
                 ("2", "bad options or input, a full disk, a memory budget a pair does not fit, "
                       "or nothing could be done (one line)"),
                 ("130, 143", "stopped by Ctrl-C / SIGTERM (one line; no file half-written)"),
                 ("", "`weathergen COMMAND --help` says what each code means for COMMAND")))
@click.version_option(__version__, "--version", prog_name="weathergen")
def cli():
    """Physically placed weather for optical-flow datasets, and weather attacks on flow networks."""


for _command in (attack, benchmark, check, demo_scene, evaluate, inspect, models_command, preview,
                 presets_command, render):
    cli.add_command(_command)


def _register():
    """Nothing to do: every command is added when this module is imported. Kept for callers
    written when commands were added on first use."""


def main(argv=None):
    return cli.main(args=argv, prog_name="weathergen")
