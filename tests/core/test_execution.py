"""Executors and accounting without a Ray cluster: the option's errors, where a pair ran, the
progress clock."""

from __future__ import annotations

import os
import socket
import sys

import pytest
from click.testing import CliRunner

from weathergen.errors import ConfigError
from weathergen.execution import RunClock, check_executor, where_ran


def test_unknown_executor_is_refused():
    with pytest.raises(ConfigError, match="local, ray"):
        check_executor("dask")


@pytest.mark.parametrize("command", ["render", "attack"])
def test_ray_missing_says_how_to_install_it(monkeypatch, tmp_path, command):
    from weathergen.cli.main import _register, cli

    monkeypatch.setitem(sys.modules, "ray", None)         # import ray -> ImportError
    _register()
    result = CliRunner().invoke(cli, [command, "--executor", "ray", "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert "--executor ray needs Ray" in result.output
    assert "pip install 'weathergen[ray]'" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "o").exists()


def test_where_ran_names_this_process():
    ran = where_ran("cpu")
    assert ran == {"host": socket.gethostname(), "pid": os.getpid(), "worker": None,
                   "device": "cpu"}


def test_run_clock_rate_and_finish():
    now = [100.0]
    clock = RunClock(10, now=lambda: now[0])
    assert clock.per_hour() is None and clock.describe() == "0/10 pairs"
    clock.add(computed=False)              # finished by an earlier run: done, but not in the rate
    now[0] += 60.0
    clock.add()
    clock.add()                            # two pairs computed in one minute
    assert clock.done == 3
    assert clock.per_hour() == pytest.approx(120.0)
    assert clock.remaining_seconds() == pytest.approx(7 * 30.0)
    assert clock.describe().startswith("3/10 pairs, 120.0 pairs/h, finish ~ ")
    assert clock.describe().endswith("(4 min)")
