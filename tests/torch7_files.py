"""Writing Torch7 binary files for the tests, from the format's description (type tag, body;
little-endian; see weathergen/io/torch7.py), independently of the reader: numbers, strings,
booleans, tables, tensors over a shared storage, and objects of other classes. Objects passed
twice are written once and referred to by index afterwards, as Torch7 does."""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

NIL, NUMBER, STRING, TABLE, TORCH, BOOLEAN, FUNCTION = 0, 1, 2, 3, 4, 5, 6
TYPES = {np.dtype("<f4"): "Float", np.dtype("<f8"): "Double", np.dtype("<i8"): "Long",
         np.dtype("<i4"): "Int", np.dtype("<u1"): "Byte"}


@dataclass
class Module:
    """An object of a Torch7 class such as ``nn.Sequential``: written as its class and a table."""
    class_name: str
    fields: dict = field(default_factory=dict)


@dataclass
class Tensor:
    """A tensor view of ``storage`` (a 1-D array): sizes, strides, 0-based offset."""
    storage: np.ndarray
    sizes: tuple
    strides: tuple
    offset: int = 0
    class_name: str = ""


def tensor(array: np.ndarray, class_name: str = "") -> Tensor:
    """A contiguous tensor holding ``array``."""
    array = np.ascontiguousarray(array)
    strides = tuple(s // array.itemsize for s in array.strides)
    return Tensor(array.reshape(-1), array.shape, strides, 0, class_name)


class Writer:
    def __init__(self):
        self.out = bytearray()
        self.index = {}

    def int32(self, v):
        self.out += struct.pack("<i", v)

    def int64(self, v):
        self.out += struct.pack("<q", v)

    def string(self, s):
        raw = s.encode() if isinstance(s, str) else s
        self.int32(len(raw))
        self.out += raw

    def _ref(self, obj) -> bool:
        """Write the reference index; True if ``obj`` was written before."""
        if id(obj) in self.index:
            self.int32(self.index[id(obj)])
            return True
        self.index[id(obj)] = len(self.index) + 1
        self.int32(self.index[id(obj)])
        return False

    def value(self, v):
        if v is None:
            self.int32(NIL)
        elif isinstance(v, bool):
            self.int32(BOOLEAN)
            self.int32(1 if v else 0)
        elif isinstance(v, (int, float)):
            self.int32(NUMBER)
            self.out += struct.pack("<d", float(v))
        elif isinstance(v, (str, bytes)):
            self.int32(STRING)
            self.string(v)
        elif isinstance(v, dict):
            self.int32(TABLE)
            if not self._ref(v):
                self.int32(len(v))
                for key, item in v.items():
                    self.value(key)
                    self.value(item)
        elif isinstance(v, Tensor):
            self.int32(TORCH)
            if not self._ref(v):
                kind = v.class_name or TYPES[v.storage.dtype]
                self.string("V 1")
                self.string(f"torch.{kind}Tensor")
                self.int32(len(v.sizes))
                for n in v.sizes:
                    self.int64(n)
                for s in v.strides:
                    self.int64(s)
                self.int64(v.offset + 1)
                self._storage(v.storage, kind)
        elif isinstance(v, Module):
            self.int32(TORCH)
            if not self._ref(v):
                self.string("V 1")
                self.string(v.class_name)
                self.value(v.fields)
        else:
            raise TypeError(type(v))

    def _storage(self, storage: np.ndarray, kind: str):
        self.int32(TORCH)
        if not self._ref(storage):
            self.string("V 1")
            self.string(f"torch.{kind}Storage")
            self.int64(storage.size)
            self.out += storage.astype(storage.dtype.newbyteorder("<")).tobytes()


def write_torch7(path: Path, obj) -> Path:
    writer = Writer()
    writer.value(obj)
    Path(path).write_bytes(bytes(writer.out))
    return Path(path)


def spynet_level(convs: list, flat: bool = True, class_name: str = "cudnn.SpatialConvolution",
                 wrap: bool = False) -> Module:
    """One SpyNet level as the authors saved it: an ``nn.Sequential`` of five convolutions with
    ReLUs between, every weight and bias a view of one flat storage (``flat``, as after
    ``getParameters()``), optionally inside an ``nn.DataParallelTable``. ``convs``: five
    (weight, bias) float32 arrays."""
    storage = np.concatenate([np.concatenate([w.ravel(), b.ravel()]) for w, b in convs])
    modules, at = {}, 0
    for i, (w, b) in enumerate(convs):
        if flat:
            wt = Tensor(storage, w.shape, tuple(s // 4 for s in np.ascontiguousarray(w).strides),
                        at, "Cuda")
            bt = Tensor(storage, b.shape, (1,), at + w.size, "Cuda")
        else:
            wt, bt = tensor(w), tensor(b)
        at += w.size + b.size
        conv = Module(class_name, {"weight": wt, "bias": bt, "nInputPlane": w.shape[1],
                                   "nOutputPlane": w.shape[0], "kW": 7, "kH": 7, "padW": 3,
                                   "padH": 3, "gradWeight": tensor(np.zeros_like(w))})
        modules[len(modules) + 1] = conv
        if i < len(convs) - 1:
            modules[len(modules) + 1] = Module("cudnn.ReLU", {"inplace": True})
    sequential = Module("nn.Sequential", {"modules": modules, "train": False,
                                          "output": tensor(np.zeros(0, np.float32), "Cuda")})
    if wrap:
        return Module("nn.DataParallelTable", {"modules": {1: sequential}})
    return sequential
