"""Compressed ``.npz`` files whose 0-d entries are gathered in one JSON entry, ``scalars``.

numpy stores every array of an ``.npz`` as its own zip member, which costs about 170 bytes (the
zip headers and the ``.npy`` header) whatever the array holds. A particle-metadata file has some
twenty 0-d entries (the pair, its seed, the render settings, ...): as separate members they took
more room than a fog record's particles. Here they are one member, ``scalars``: a JSON object
mapping each name to ``[value, dtype]`` (the numpy dtype string, so that the entry reads back as
the same 0-d array). Entries named in ``keep`` (the format versions, which a reader must find
whatever else changed) stay members of their own.

``numpy.load`` reads these files as any ``.npz``: ``json.loads(str(data["scalars"]))`` gives the
gathered entries. :func:`read_npz` gives every entry as its own array again, so code reading a
file sees the same names as the code that wrote it. A file without a ``scalars`` member (the
formats before this container) reads unchanged.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np

#: The member holding every gathered 0-d entry.
SCALARS = "scalars"


def npz_bytes(arrays: dict[str, np.ndarray], keep: tuple[str, ...] = ()) -> bytes:
    """The ``.npz`` content of ``arrays`` (deflate, no pickles), 0-d entries not in ``keep``
    gathered into :data:`SCALARS`."""
    scalars, members = {}, {}
    for name, value in arrays.items():
        a = np.asarray(value)
        if a.ndim == 0 and name not in keep and a.dtype.kind in "biufU":
            scalars[name] = [a.item(), a.dtype.str]
        else:
            members[name] = a
    if SCALARS in members:
        raise ValueError(f"an array may not be named {SCALARS!r}: the gathered entries use it")
    if scalars:
        members[SCALARS] = np.array(json.dumps(scalars, separators=(",", ":")))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as archive:
        for name, a in members.items():
            npy = io.BytesIO()
            np.lib.format.write_array(npy, a, allow_pickle=False)
            # a ZipInfo of its own dates the member 1980-01-01 (as numpy's savez does): the bytes
            # depend on the content alone, not on when it was written
            member = zipfile.ZipInfo(f"{name}.npy")
            archive.writestr(member, npy.getvalue(), compress_type=zipfile.ZIP_DEFLATED,
                             compresslevel=9)
    return buf.getvalue()


def expand_scalars(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``arrays`` with the :data:`SCALARS` member (if any) turned back into its 0-d arrays.

    Raises ValueError when that member is not what :func:`npz_bytes` writes.
    """
    if SCALARS not in arrays:
        return dict(arrays)
    gathered = json.loads(str(arrays[SCALARS]))
    if not isinstance(gathered, dict):
        raise ValueError(f"'{SCALARS}' is not a JSON object")
    out = {k: v for k, v in arrays.items() if k != SCALARS}
    for name, entry in gathered.items():
        if not (isinstance(entry, list) and len(entry) == 2 and isinstance(entry[1], str)):
            raise ValueError(f"'{SCALARS}' entry {name!r} is not [value, dtype]")
        out[name] = np.array(entry[0], dtype=np.dtype(entry[1]))
    return out


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Every entry of an ``.npz`` (no pickles), gathered 0-d entries as their own arrays.

    Raises what ``numpy.load`` raises for a missing or corrupt file, and ValueError for a
    :data:`SCALARS` member that cannot be read; callers name the file in their own error.
    """
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    return expand_scalars(arrays)


__all__ = ["SCALARS", "expand_scalars", "npz_bytes", "read_npz"]
