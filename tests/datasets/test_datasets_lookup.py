"""Readers by name: the default reader, unknown names, what a reader needs."""

from __future__ import annotations

import pytest

from weathergen.cli.options import option_of
from weathergen.datasets import DATASETS, default_dataset, open_dataset
from weathergen.errors import ConfigError


def test_the_default_reader_is_the_demo_without_a_root_and_sintel_with_one():
    assert default_dataset(None) == "demo" and default_dataset("") == "demo"
    assert default_dataset("/data/MPI-Sintel") == "sintel"
    assert {"demo", "sintel"} <= set(DATASETS)


def test_a_reader_without_its_root_names_the_parameter():
    with pytest.raises(ConfigError) as missing:
        open_dataset("kitti")
    assert str(missing.value) == "dataset 'kitti' needs root, the folder it is stored in"
    assert missing.value.render(option_of) == "dataset 'kitti' needs --root, the folder it is stored in"
    with pytest.raises(ConfigError, match="unknown dataset 'hd1k'; known: custom, demo"):
        open_dataset("hd1k")
