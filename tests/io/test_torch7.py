"""The Torch7 reader against files written in the documented format (tests/torch7_files.py)."""

from __future__ import annotations

import numpy as np
import pytest
from torch7_files import Module, Tensor, tensor, write_torch7

from weathergen.errors import FormatError
from weathergen.io.torch7 import Torch7Object, read_torch7


def test_plain_values_and_tables(tmp_path):
    path = write_torch7(tmp_path / "v.t7", {"a": 1.5, "name": "spy", "flag": True, "none": None,
                                            1: "first", 2: {"nested": -3.0}})
    got = read_torch7(path)
    assert got == {"a": 1.5, "name": "spy", "flag": True, "none": None, 1: "first",
                   2: {"nested": -3.0}}
    assert list(k for k in got if isinstance(k, int)) == [1, 2]   # Lua array keys as ints


@pytest.mark.parametrize("dtype, kind", [(np.float32, ""), (np.float64, ""), (np.int64, ""),
                                         (np.float32, "Cuda")])
def test_tensors_keep_shape_type_and_values(tmp_path, dtype, kind):
    array = np.arange(24, dtype=dtype).reshape(2, 3, 4) - 7
    got = read_torch7(write_torch7(tmp_path / "t.t7", tensor(array, kind)))
    assert got.dtype == np.dtype(dtype) and got.shape == (2, 3, 4)
    assert np.array_equal(got, array)


def test_views_into_one_storage_with_offsets_and_strides(tmp_path):
    storage = np.arange(20, dtype=np.float32)
    first = Tensor(storage, (2, 3), (3, 1), offset=2)           # elements 2..7
    transposed = Tensor(storage, (3, 2), (1, 3), offset=2)      # the same, transposed
    column = Tensor(storage, (4,), (5,), offset=4)              # 4, 9, 14, 19
    got = read_torch7(write_torch7(tmp_path / "v.t7", {1: first, 2: transposed, 3: column}))
    assert np.array_equal(got[1], storage[2:8].reshape(2, 3))
    assert np.array_equal(got[2], storage[2:8].reshape(2, 3).T)
    assert np.array_equal(got[3], [4, 9, 14, 19])


def test_objects_of_other_classes_and_shared_references(tmp_path):
    shared = {"k": 2.0}
    weight = tensor(np.ones((2, 2), np.float32))
    model = Module("nn.Sequential", {"modules": {1: Module("nn.Linear", {"weight": weight}),
                                                 2: Module("nn.Linear", {"weight": weight})},
                                     "a": shared, "b": shared})
    got = read_torch7(write_torch7(tmp_path / "m.t7", model))
    assert isinstance(got, Torch7Object) and got.class_name == "nn.Sequential"
    first, second = got.fields["modules"][1], got.fields["modules"][2]
    assert first.class_name == "nn.Linear" and first.fields["weight"] is second.fields["weight"]
    assert got.fields["a"] is got.fields["b"] and got.fields["a"] == {"k": 2.0}


def test_truncated_file_fails_naming_it(tmp_path):
    path = write_torch7(tmp_path / "t.t7", tensor(np.ones((4, 4), np.float32)))
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(FormatError, match=r"t\.t7: .*truncated"):
        read_torch7(path)


@pytest.mark.parametrize("content, message", [
    (b"\x07\x00\x00\x00", "not a Torch7 binary file"),
    (b"PK\x03\x04zipfile", "not a Torch7 binary file"),
    (b"\x02", "too short"),
    (b"\x03\x00\x00\x00\x01\x00\x00\x00\xff\xff\xff\x7f", "cannot hold"),
    # a table {f = <function>}
    (b"\x03\x00\x00\x00\x01\x00\x00\x00\x01\x00\x00\x00\x02\x00\x00\x00\x01\x00\x00\x00f"
     b"\x06\x00\x00\x00\x02\x00\x00\x00", "Lua function"),
])
def test_files_that_are_not_torch7_fail_with_one_line(tmp_path, content, message):
    path = tmp_path / "bad.t7"
    path.write_bytes(content)
    with pytest.raises(FormatError) as err:
        read_torch7(path)
    assert str(err.value).startswith(str(path)) and message in str(err.value)
    assert "\n" not in str(err.value)


def test_a_tensor_reaching_beyond_its_storage_is_refused(tmp_path):
    path = write_torch7(tmp_path / "t.t7", Tensor(np.zeros(4, np.float32), (3,), (2,), 0))
    with pytest.raises(FormatError, match="reaches element 5 of a storage of 4"):
        read_torch7(path)


def test_missing_file(tmp_path):
    with pytest.raises(FormatError, match="cannot be read"):
        read_torch7(tmp_path / "none.t7")
