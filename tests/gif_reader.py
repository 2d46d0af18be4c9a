"""A GIF decoder for the tests: it reads what :mod:`weathergen.io.gif` writes, and any GIF whose
frames cover the whole screen with a global or a local palette (interlaced frames and partial
frames are not supported: :class:`~weathergen.errors.FormatError` says so)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from weathergen.errors import FormatError
from weathergen.io.gif import _EXTENSION, _IMAGE, _MAX_CODES, _TRAILER


class _Reader:
    def __init__(self, data: bytes, path: Path):
        self.data, self.pos, self.path = data, 0, path

    def take(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise FormatError(self.path, "truncated GIF")
        chunk = self.data[self.pos:self.pos + n]
        self.pos += n
        return chunk

    def byte(self) -> int:
        return self.take(1)[0]

    def blocks(self) -> bytes:
        out = bytearray()
        while True:
            n = self.byte()
            if n == 0:
                return bytes(out)
            out += self.take(n)


def _lzw_decode(data: bytes, min_bits: int, count: int, path: Path) -> np.ndarray:
    """Palette indices of ``count`` pixels from LZW-coded ``data``. Shape: -> (count,) uint8."""
    clear, end = 1 << min_bits, (1 << min_bits) + 1
    bits = np.unpackbits(np.frombuffer(data, np.uint8), bitorder="little")
    out = bytearray()
    table: list[bytes] = []
    width, pos, prev = min_bits + 1, 0, None

    def reset():
        table[:] = [bytes([i]) for i in range(clear)] + [b"", b""]

    reset()
    weights = 1 << np.arange(12)
    while pos + width <= len(bits):
        code = int(bits[pos:pos + width] @ weights[:width])
        pos += width
        if code == clear:
            reset()
            width, prev = min_bits + 1, None
            continue
        if code == end:
            break
        if prev is None:
            if code >= len(table):
                raise FormatError(path, f"GIF: LZW code {code} before any table entry")
            entry = table[code]
        else:
            if code < len(table):
                entry = table[code]
                new = table[prev] + entry[:1]
            elif code == len(table):
                entry = new = table[prev] + table[prev][:1]
            else:
                raise FormatError(path, f"GIF: LZW code {code} beyond the table ({len(table)})")
            if len(table) < _MAX_CODES:
                table.append(new)
                if len(table) == 1 << width and width < 12:
                    width += 1
        out += entry
        prev = code
    if len(out) < count:
        raise FormatError(path, f"GIF frame holds {len(out)} pixels, expected {count}")
    return np.frombuffer(bytes(out[:count]), np.uint8)


def decode_gif(data: bytes, path: str | Path = "<gif>") -> tuple[list[np.ndarray], list[int]]:
    """The frames of a GIF and their delays (hundredths of a second).

    Shape: returns frames (H, W, 3) uint8 RGB. Raises FormatError naming ``path`` for a file that is
    not a GIF or uses what this reader does not support (interlacing, frames smaller than the
    screen).
    """
    path = Path(path)
    r = _Reader(data, path)
    if r.take(6) not in (b"GIF87a", b"GIF89a"):
        raise FormatError(path, "not a GIF file")
    w, h, flags, _, _ = struct.unpack("<HHBBB", r.take(7))
    global_palette = None
    if flags & 0x80:
        global_palette = np.frombuffer(r.take(3 << ((flags & 7) + 1)), np.uint8).reshape(-1, 3)
    frames, delays, delay = [], [], 0
    while True:
        kind = r.byte()
        if kind == _TRAILER:
            return frames, delays
        if kind == _EXTENSION:
            label = r.byte()
            body = r.blocks()
            if label == 0xF9 and len(body) >= 3:
                delay = struct.unpack("<H", body[1:3])[0]
            continue
        if kind != _IMAGE:
            raise FormatError(path, f"GIF: unexpected block 0x{kind:02x}")
        x, y, fw, fh, fflags = struct.unpack("<HHHHB", r.take(9))
        if (x, y, fw, fh) != (0, 0, w, h):
            raise FormatError(path, "GIF frames smaller than the screen are not supported")
        if fflags & 0x40:
            raise FormatError(path, "interlaced GIF frames are not supported")
        palette = global_palette
        if fflags & 0x80:
            palette = np.frombuffer(r.take(3 << ((fflags & 7) + 1)), np.uint8).reshape(-1, 3)
        if palette is None:
            raise FormatError(path, "GIF frame without a palette")
        min_bits = r.byte()
        if not 2 <= min_bits <= 11:
            raise FormatError(path, f"GIF: LZW minimum code size {min_bits}")
        indices = _lzw_decode(r.blocks(), min_bits, w * h, path)
        if int(indices.max(initial=0)) >= len(palette):
            raise FormatError(path, "GIF pixel beyond its palette")
        frames.append(palette[indices].reshape(h, w, 3))
        delays.append(delay)


def read_gif(path: str | Path) -> tuple[list[np.ndarray], list[int]]:
    """The frames and delays of a GIF file (see :func:`decode_gif`)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    return decode_gif(data, path)
