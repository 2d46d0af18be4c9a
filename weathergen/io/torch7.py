"""Files written by ``torch.save`` of Torch7, the Lua framework (its "binary" format).

Some networks were released as Torch7 files only (SpyNet's ``modelL1_F.t7`` ...). This module
reads the object graph such a file holds into Python values, without Lua or the old
``torch.utils.serialization``:

- numbers -> ``float``, strings -> ``str`` (``bytes`` when not UTF-8), booleans -> ``bool``,
  ``nil`` -> ``None``;
- Lua tables -> ``dict`` (keys as stored: ``str``, or ``int`` for whole numbers, so that a
  Lua array ``{a, b}`` becomes ``{1: a, 2: b}``);
- tensors and storages (``torch.FloatTensor``, ``torch.CudaTensor``, ...) -> NumPy arrays (copies,
  in the tensor's shape; CUDA types are stored on disk like their CPU types);
- every other class (``nn.Sequential``, ``cudnn.SpatialConvolution``, ...) ->
  :class:`Torch7Object`, the class name and the table of its fields.

An object referred to twice in the file is read once and shared, as Torch7 does. Lua functions
(a model saved with closures) are not supported and fail with a :class:`FormatError`.

The format: each value is a 4-byte type tag followed by its body. Numbers are 8-byte doubles,
booleans and lengths of strings 4-byte integers, sizes of tensors and storages 8-byte integers,
all little-endian. A table or class object starts with a 4-byte reference index (a repeat of an
index means "the object read before"); a class object then has a version string ``"V <n>"``
(absent in very old files) and its class name; a tensor body is the number of dimensions, the
sizes, the strides, the 1-based storage offset and the storage object; a storage body is the
number of elements and the raw elements; other classes store a table of fields.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import FormatError

_NIL, _NUMBER, _STRING, _TABLE, _TORCH, _BOOLEAN = 0, 1, 2, 3, 4, 5
_FUNCTIONS = (6, 7, 8)          # function, legacy recursive function, recursive function

#: Element types of Torch7's tensor and storage classes (``torch.<Kind>Tensor``).
_KINDS = {"Byte": "<u1", "Char": "<i1", "Short": "<i2", "Int": "<i4", "Long": "<i8",
          "Float": "<f4", "Double": "<f8", "Half": "<f2"}
#: cutorch's names: ``torch.CudaTensor`` holds floats, ``torch.Cuda<Kind>Tensor`` the others.
_CUDA_KINDS = {"": "Float", **{k: k for k in _KINDS}}


@dataclass
class Torch7Object:
    """An object of a Torch7 class other than tensors and storages: its class name
    (``nn.Sequential``) and its fields (``weight``, ``modules``, ...)."""

    class_name: str
    fields: dict = field(default_factory=dict)


def read_torch7(path: str | Path) -> Any:
    """The object a Torch7 binary file holds (see the module documentation for the types).

    Raises:
        FormatError: the file is missing, truncated, not in Torch7's binary format, or holds
            something this reader does not support (Lua functions); the message names the file.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise FormatError(path, f"cannot be read ({exc.strerror or exc})") from None
    if len(data) < 4:
        raise FormatError(path, "is too short for a Torch7 file")
    reader = _Reader(data, path)
    first = reader.int32()
    if first not in (_NIL, _NUMBER, _STRING, _TABLE, _TORCH, _BOOLEAN):
        raise FormatError(path, f"not a Torch7 binary file (it starts with type tag {first}); "
                                f"expected a file saved by Torch7's torch.save")
    reader.pos = 0
    obj = reader.value()
    return obj


class _Reader:
    def __init__(self, data: bytes, path: Path):
        self.data = data
        self.path = path
        self.pos = 0
        self.seen: dict[int, Any] = {}

    # -- primitives ----------------------------------------------------------------------------
    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise FormatError(self.path, f"ends early: {n} bytes wanted at byte {self.pos} of "
                                         f"{len(self.data)} (truncated or not a Torch7 file)")
        chunk = self.data[self.pos:self.pos + n]
        self.pos += n
        return chunk

    def int32(self) -> int:
        return struct.unpack("<i", self.take(4))[0]

    def int64(self) -> int:
        return struct.unpack("<q", self.take(8))[0]

    def float64(self) -> float:
        return struct.unpack("<d", self.take(8))[0]

    def string(self) -> str | bytes:
        raw = self.take(self.int32())
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            return raw

    # -- values --------------------------------------------------------------------------------
    def value(self) -> Any:
        at = self.pos
        tag = self.int32()
        if tag == _NIL:
            return None
        if tag == _NUMBER:
            return self.float64()
        if tag == _STRING:
            return self.string()
        if tag == _BOOLEAN:
            return self.int32() == 1
        if tag == _TABLE:
            return self.table()
        if tag == _TORCH:
            return self.torch_object()
        if tag in _FUNCTIONS:
            raise FormatError(self.path, f"holds a Lua function (at byte {at}), which this "
                                         f"reader does not support")
        raise FormatError(self.path, f"unknown type tag {tag} at byte {at} (damaged, or not a "
                                     f"Torch7 binary file)")

    def table(self) -> dict:
        index = self.int32()
        if index in self.seen:
            return self.seen[index]
        out: dict = {}
        self.seen[index] = out
        for _ in range(self._count(self.int32(), 2)):
            key = self.value()
            if isinstance(key, float) and key.is_integer():
                key = int(key)
            out[key] = self.value()
        return out

    def torch_object(self) -> Any:
        index = self.int32()
        if index in self.seen:
            return self.seen[index]
        version = self.string()
        if isinstance(version, str) and version.startswith("V "):
            class_name = self.string()
        else:                            # files of the first Torch7 versions: no version string
            class_name = version
        if not isinstance(class_name, str):
            raise FormatError(self.path, f"a class name that is not text at byte {self.pos}")
        dtype = _element_type(class_name)
        if dtype is not None and class_name.endswith("Storage"):
            obj = self.storage(dtype)
        elif dtype is not None and class_name.endswith("Tensor"):
            obj = self.tensor(dtype, class_name)
        else:
            obj = Torch7Object(class_name)
            self.seen[index] = obj      # before the fields: they may refer back to it
            fields = self.value()
            obj.fields = fields if isinstance(fields, dict) else {"value": fields}
            return obj
        self.seen[index] = obj
        return obj

    def storage(self, dtype: np.dtype) -> np.ndarray:
        n = self._count(self.int64(), dtype.itemsize)
        return np.frombuffer(self.take(n * dtype.itemsize), dtype=dtype).copy()

    def tensor(self, dtype: np.dtype, class_name: str) -> np.ndarray:
        ndim = self.int32()
        if not 0 <= ndim <= 64:
            raise FormatError(self.path, f"{class_name} with {ndim} dimensions at byte {self.pos}")
        sizes = [self.int64() for _ in range(ndim)]
        strides = [self.int64() for _ in range(ndim)]
        offset = self.int64() - 1      # Lua counts from 1
        storage = self.value()
        if ndim == 0 or any(s == 0 for s in sizes):
            return np.zeros(sizes if ndim else (0,), dtype=dtype)
        if not isinstance(storage, np.ndarray):
            raise FormatError(self.path, f"{class_name} of size {tuple(sizes)} without a storage")
        if min(sizes) < 0 or min(strides) < 0:
            raise FormatError(self.path, f"{class_name} with negative sizes or strides")
        last = offset + sum((n - 1) * s for n, s in zip(sizes, strides))
        if offset < 0 or last >= storage.size:
            raise FormatError(self.path, f"{class_name} of size {tuple(sizes)} reaches element "
                                         f"{last + 1} of a storage of {storage.size}")
        view = np.lib.stride_tricks.as_strided(
            storage[offset:], shape=sizes, strides=[s * storage.itemsize for s in strides],
            writeable=False)
        return np.array(view, dtype=dtype)

    def _count(self, n: int, min_bytes: int) -> int:
        """``n`` elements of at least ``min_bytes`` each must fit in the rest of the file."""
        if n < 0 or n * min_bytes > len(self.data) - self.pos:
            raise FormatError(self.path, f"a count of {n} at byte {self.pos} that the file "
                                         f"cannot hold (truncated or damaged)")
        return n


def _element_type(class_name: str) -> np.dtype | None:
    """The NumPy type of ``torch.<Kind>Tensor`` / ``torch.Cuda<Kind>Storage``; ``None`` for
    other classes."""
    if not class_name.startswith("torch."):
        return None
    stem = class_name[len("torch."):]
    for suffix in ("Tensor", "Storage"):
        if stem.endswith(suffix):
            kind = stem[:-len(suffix)]
            if kind.startswith("Cuda"):
                kind = _CUDA_KINDS.get(kind[len("Cuda"):], "")
            code = _KINDS.get(kind)
            return None if code is None else np.dtype(code)
    return None
