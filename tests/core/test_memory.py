"""The memory a run may still take (weathergen.memory), read from files written here as the kernel
writes them: /proc/meminfo, a control group's limit and usage (v2 and v1), and the budget variable."""

from __future__ import annotations

import pytest

from weathergen.errors import ConfigError
from weathergen.memory import BUDGET_VARIABLE, available_memory, human_bytes, parse_bytes


def _machine(root, available_kb=8_000_000, cgroup=None):
    (root / "proc" / "self").mkdir(parents=True)
    (root / "proc" / "meminfo").write_text(f"MemTotal:       16000000 kB\nMemFree:  1000 kB\n"
                                           f"MemAvailable:   {available_kb} kB\n")
    (root / "proc" / "self" / "cgroup").write_text(cgroup or "0::/\n")
    return root


def test_mem_available_is_read_from_meminfo(tmp_path):
    got = available_memory({}, _machine(tmp_path))
    assert got == (8_000_000 * 1024, "MemAvailable")


def test_a_control_groups_limit_less_its_usage_wins_when_smaller(tmp_path):
    root = _machine(tmp_path, cgroup="0::/job/42\n")
    group = root / "sys" / "fs" / "cgroup" / "job" / "42"
    group.mkdir(parents=True)
    (group / "memory.max").write_text(f"{6 << 30}\n")
    (group / "memory.current").write_text(f"{2 << 30}\n")
    assert available_memory({}, root) == (4 << 30, "the control group's memory.max")
    (group / "memory.max").write_text("max\n")               # no limit: the machine's figure
    assert available_memory({}, root).source == "MemAvailable"


def test_a_v1_control_group_limit_counts_and_its_no_limit_does_not(tmp_path):
    root = _machine(tmp_path, cgroup="4:memory:/slurm/job7\n1:cpu:/\n")
    group = root / "sys" / "fs" / "cgroup" / "memory" / "slurm" / "job7"
    group.mkdir(parents=True)
    (group / "memory.limit_in_bytes").write_text(f"{3 << 30}\n")
    (group / "memory.usage_in_bytes").write_text(f"{1 << 30}\n")
    assert available_memory({}, root) == (2 << 30, "the control group's memory.limit_in_bytes")
    (group / "memory.limit_in_bytes").write_text("9223372036854771712\n")
    assert available_memory({}, root).source == "MemAvailable"


def test_the_budget_variable_sets_the_budget(tmp_path):
    root = _machine(tmp_path)
    assert available_memory({BUDGET_VARIABLE: "512M"}, root) == (512 << 20, BUDGET_VARIABLE)
    assert available_memory({BUDGET_VARIABLE: " "}, root).source == "MemAvailable"
    with pytest.raises(ConfigError, match=f"{BUDGET_VARIABLE}: 'plenty' is not an amount"):
        available_memory({BUDGET_VARIABLE: "plenty"}, root)


def test_nothing_known_is_none(tmp_path):
    assert available_memory({}, tmp_path) is None


@pytest.mark.parametrize("text, expected", [("1024", 1024), ("2K", 2048), ("1.5G", 3 << 29),
                                            ("64MiB", 64 << 20), ("3 gb", 3 << 30)])
def test_amounts_of_memory_parse(text, expected):
    assert parse_bytes(text) == expected


def test_amounts_print_in_binary_units():
    assert [human_bytes(n) for n in (512, 1536, 64 << 20, 3 << 30)] == [
        "512 B", "1.5 KiB", "64.0 MiB", "3.0 GiB"]
