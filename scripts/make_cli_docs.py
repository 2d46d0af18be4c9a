"""Write docs/cli.md, the command-line reference, from the commands' own ``--help``.

    python scripts/make_cli_docs.py            # rewrite docs/cli.md
    python scripts/make_cli_docs.py --check    # exit 1 when docs/cli.md differs from --help

The page is the ``--help`` text of ``weathergen`` and of every command, formatted by click at a
fixed width (so that it does not depend on the terminal), after a short introduction. A test
(tests/test_cli_docs.py) fails when the page and the commands' help differ: after changing an
option, run this script.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import click

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "cli.md"
WIDTH = 100

INTRO = """\
# Command-line reference

Generated from `weathergen --help` and each command's `--help` by `scripts/make_cli_docs.py`
(`tests/test_cli_docs.py` checks that it matches): edit the commands' help texts, not this page.
What the commands do and write is explained in [render.md](render.md) (render outputs),
[attack.md](attack.md) (attack, benchmark, evaluate), [datasets.md](datasets.md) (the options
that choose data), [models.md](models.md) (networks and checkpoints) and [scale.md](scale.md)
(batches, Ray, job arrays); what they promise when things go wrong in
[guarantees.md](guarantees.md).

## Errors and exit codes

Bad input that concerns the whole run (a missing root, a scene folder without frames, an invalid
preset key or value, a preset or scale file that is not UTF-8 text, a scale for a scene that does
not exist, an unknown preset, dataset or model name, a checkpoint that is not one, a device that is
not there) gives one line naming the file or option and the problem, and exit code 2, before
anything is written. Problems of single pairs (missing depth or camera files, a corrupt header,
images and depth of different sizes, non-finite or non-positive depth, stored particles of another
pair, dataset or preset) are found as each pair is read: `render` and `attack` report each such
pair, finish the others and exit with 1; when every selected pair fails, `render` exits with 2 and
removes the output folder it created (nothing is written). `check` exits with 1 when some selected
pairs cannot be read. A full disk or an unwritable folder stops the run with one line and exit
code 2, the finished pairs recorded. An interrupted run exits with 130 (Ctrl-C) or 143 (SIGTERM)
and is finished by `--resume`.
"""


def help_text(command: click.Command, path: list[str], parent: click.Context | None) -> str:
    """``command``'s ``--help`` as ``weathergen PATH --help`` prints it, ``WIDTH`` columns wide."""
    ctx = click.Context(command, info_name=path[-1], parent=parent, terminal_width=WIDTH,
                        max_content_width=WIDTH)
    return ctx.get_help()


def page() -> str:
    """The whole page: the introduction, then one section per command, sorted by name (the
    commands of this checkout, whatever weathergen is installed)."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from weathergen.cli.main import cli

    root = click.Context(cli, info_name="weathergen", terminal_width=WIDTH, max_content_width=WIDTH,
                         **cli.context_settings)       # -h and --help, as the group declares
    parts = [INTRO, "## `weathergen`", "", "```text", root.get_help(), "```", ""]
    for name in sorted(cli.list_commands(root)):
        command = cli.get_command(root, name)
        parts += [f"## `weathergen {name}`", "", "```text",
                  help_text(command, ["weathergen", name], root), "```", ""]
    return "\n".join(parts)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 when it differs")
    args = parser.parse_args(argv)
    text = page()
    if args.check:
        if not PAGE.exists() or PAGE.read_text() != text:
            print(f"{PAGE.relative_to(ROOT)} differs from the commands' --help: run "
                  f"python scripts/make_cli_docs.py", file=sys.stderr)
            return 1
        return 0
    if PAGE.exists() and PAGE.read_text() == text:
        print(f"{PAGE.relative_to(ROOT)}: unchanged")
        return 0
    PAGE.write_text(text)
    print(f"wrote {PAGE.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
