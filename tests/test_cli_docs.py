"""docs/cli.md, the command-line reference, is the commands' own --help (scripts/make_cli_docs.py)."""

from __future__ import annotations

import importlib.util
import re

from click.testing import CliRunner

from conftest import PROJECT_ROOT


def _script():
    spec = importlib.util.spec_from_file_location("make_cli_docs", PROJECT_ROOT / "scripts" / "make_cli_docs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_docs_cli_md_is_what_the_commands_help_says_today():
    script = _script()
    assert script.PAGE.read_text() == script.page(), \
        "docs/cli.md differs from the commands' --help: run python scripts/make_cli_docs.py"
    assert script.main(["--check"]) == 0


def test_every_command_and_option_of_the_command_line_is_in_the_reference():
    from weathergen.cli.main import cli

    text = (PROJECT_ROOT / "docs" / "cli.md").read_text()
    names = cli.list_commands(None)
    assert len(names) >= 9
    for name in names:
        section = text.split(f"## `weathergen {name}`\n", 1)[1].split("\n## ", 1)[0]
        printed = CliRunner().invoke(cli, [name, "--help"]).output
        options = set(re.findall(r"(?<![\w-])--[a-z][\w-]+", printed))
        assert options and options <= set(re.findall(r"(?<![\w-])--[a-z][\w-]+", section)), name
