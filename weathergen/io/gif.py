"""Animated GIF (GIF89a), written with numpy alone.

OpenCV's video writer cannot write GIF (its FFmpeg back end refuses the pixel format), so the
encoder is our own: every frame gets its own 256-colour palette (a frame with at most 256 colours
keeps them exactly; others get a median-cut palette of their colours at 5 bits per channel, and
every pixel the nearest palette colour), its pixels are LZW-compressed as the format prescribes
(variable code width from 9 to 12 bits, a clear code when the table of 4096 codes is full), and
the file loops forever.

A GIF's frame delay is a whole number of hundredths of a second, so each frame starts at the
hundredth nearest to its time at the frame rate: 24 fps alternates delays of 4 and 5 hundredths
(4, 4, 4, 5, ...; 24 frames take exactly one second), 10 fps is 10 each.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path
from typing import Iterable

import numpy as np

from .atomic import atomic_write_bytes

_TRAILER = 0x3B
_EXTENSION = 0x21
_IMAGE = 0x2C
_CODE_BITS = 8                 # LZW minimum code size: 256 colours
_CLEAR = 1 << _CODE_BITS
_END = _CLEAR + 1
_MAX_CODES = 4096              # 12-bit codes


def _hundredths(index: int, fps: float) -> int:
    """The hundredth of a second nearest to ``index / fps`` (halves up)."""
    return math.floor(100.0 * index / fps + 0.5)


def frame_delay(fps: float, index: int = 0) -> int:
    """The delay after frame ``index``, in hundredths of a second (at least 1): from the hundredth
    nearest to the frame's time ``index / fps`` to that nearest to the next frame's, so that the
    frames keep the frame rate on average and never drift from it by half a hundredth."""
    return max(1, _hundredths(index + 1, fps) - _hundredths(index, fps))


# -- palettes ---------------------------------------------------------------------------------

def palette_indices(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A frame as 256 palette colours and an index per pixel.

    Shape: rgb (H, W, 3) uint8 -> palette (256, 3) uint8, indices (H, W) uint8. A frame of at most
    256 distinct colours is kept exactly; otherwise the palette is a median cut of its colours
    reduced to 5 bits per channel, weighted by how many pixels have them.
    """
    flat = np.ascontiguousarray(rgb, np.uint8).reshape(-1, 3)
    packed = (flat[:, 0].astype(np.int32) << 16) | (flat[:, 1].astype(np.int32) << 8) | flat[:, 2]
    colours, inverse = np.unique(packed, return_inverse=True)
    palette = np.zeros((256, 3), np.uint8)
    if colours.size <= 256:
        palette[:colours.size] = np.stack((colours >> 16, (colours >> 8) & 255, colours & 255), 1)
        return palette, inverse.reshape(rgb.shape[:2]).astype(np.uint8)
    bins = ((flat[:, 0] >> 3).astype(np.int32) << 10) | ((flat[:, 1] >> 3).astype(np.int32) << 5) \
        | (flat[:, 2] >> 3)
    used, bin_of, counts = np.unique(bins, return_inverse=True, return_counts=True)
    # the mean colour of each occupied bin, weighted by its pixels
    means = np.stack([np.bincount(bin_of, flat[:, c].astype(np.float64)) for c in range(3)], 1)
    means /= counts[:, None]
    centres = _median_cut(means, counts.astype(np.float64), 256)
    palette[:len(centres)] = np.clip(np.round(centres), 0, 255).astype(np.uint8)
    nearest = _nearest(means, palette[:len(centres)].astype(np.float64))
    return palette, nearest[bin_of].reshape(rgb.shape[:2]).astype(np.uint8)


def _median_cut(colours: np.ndarray, weights: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` colours: the weighted means of boxes made by halving, again and again, the
    box with the widest weighted spread along its widest channel at its weighted median.
    Shape: (M, 3), (M,) -> (K, 3) with K <= n."""
    boxes = [np.arange(len(colours))]
    while len(boxes) < n:
        scores = []
        for box in boxes:
            span = np.ptp(colours[box], axis=0) if len(box) > 1 else np.zeros(3)
            scores.append(span.max() * np.sqrt(weights[box].sum()))
        i = int(np.argmax(scores))
        if scores[i] <= 0:
            break                                   # every box holds one colour
        box = boxes.pop(i)
        channel = int(np.argmax(np.ptp(colours[box], axis=0)))
        order = box[np.argsort(colours[box, channel], kind="stable")]
        cum = np.cumsum(weights[order])
        cut = int(np.searchsorted(cum, cum[-1] / 2)) + 1
        cut = min(max(cut, 1), len(order) - 1)      # both halves keep a colour
        boxes += [order[:cut], order[cut:]]
    return np.stack([(colours[b] * weights[b, None]).sum(0) / weights[b].sum() for b in boxes])


def _nearest(colours: np.ndarray, palette: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Index of the nearest palette colour of each colour. Shape: (M, 3), (K, 3) -> (M,)."""
    out = np.empty(len(colours), np.int64)
    for s in range(0, len(colours), chunk):
        d = ((colours[s:s + chunk, None, :] - palette[None]) ** 2).sum(-1)
        out[s:s + chunk] = d.argmin(1)
    return out


# -- LZW ----------------------------------------------------------------------------------------

def _lzw_codes(indices: bytes) -> tuple[list[int], list[int]]:
    """The LZW codes of a frame's palette indices and the bit width each is written with.

    A code is written with as many bits as the largest code the decoder may have in its table at
    that point (9 to 12); when the table is full a clear code starts it afresh.
    """
    codes, widths = [_CLEAR], [_CODE_BITS + 1]
    table: dict[int, int] = {}
    next_code = _END + 1
    prefix = indices[0]
    for byte in indices[1:]:
        key = (prefix << 8) | byte
        code = table.get(key)
        if code is not None:
            prefix = code
            continue
        codes.append(prefix)
        widths.append((next_code - 1).bit_length())
        if next_code < _MAX_CODES:
            table[key] = next_code
            next_code += 1
        else:
            codes.append(_CLEAR)
            widths.append(12)
            table.clear()
            next_code = _END + 1
        prefix = byte
    codes.append(prefix)
    widths.append((next_code - 1).bit_length())
    # the decoder has added an entry for the last code by now: the end code may be a bit wider
    codes.append(_END)
    widths.append(min(12, next_code.bit_length()))
    return codes, [max(_CODE_BITS + 1, w) for w in widths]


def _pack_codes(codes: list[int], widths: list[int]) -> bytes:
    """Codes of the given widths as a little-endian bit stream (least significant bit first)."""
    c = np.asarray(codes, np.int64)
    w = np.asarray(widths, np.int64)
    bits = ((c[:, None] >> np.arange(12)) & 1).astype(np.uint8)
    bits = bits[np.arange(12)[None, :] < w[:, None]]       # row by row: each code's own bits
    return np.packbits(bits, bitorder="little").tobytes()


def _sub_blocks(data: bytes) -> bytes:
    """Data as GIF sub-blocks (a length byte, up to 255 bytes) and the block terminator."""
    out = bytearray()
    for s in range(0, len(data), 255):
        chunk = data[s:s + 255]
        out.append(len(chunk))
        out += chunk
    out.append(0)
    return bytes(out)


# -- writing ----------------------------------------------------------------------------------

def encode_gif(frames: Iterable[np.ndarray], fps: float) -> bytes:
    """An animated, endlessly looping GIF of ``frames``, played at ``fps`` (each frame to the
    nearest 1/100 s, :func:`frame_delay`).

    Shape: frames (H, W, 3) uint8 RGB, all of one size. Raises ValueError for no frame or frames
    of different sizes.
    """
    out = bytearray()
    size = None
    for index, rgb in enumerate(frames):
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"GIF frames must be (H, W, 3) uint8, got {rgb.dtype} {rgb.shape}")
        h, w = rgb.shape[:2]
        if size is None:
            size = (h, w)
            if not (0 < w < 65536 and 0 < h < 65536):
                raise ValueError(f"GIF frames must be 1 to 65535 pixels wide and high, got {w}x{h}")
            out += b"GIF89a" + struct.pack("<HHBBB", w, h, 0, 0, 0)    # no global palette
            # NETSCAPE2.0: loop forever
            out += bytes([_EXTENSION, 0xFF, 11]) + b"NETSCAPE2.0" + bytes([3, 1, 0, 0, 0])
        elif (h, w) != size:
            raise ValueError(f"GIF frames must share one size: {size[1]}x{size[0]}, then {w}x{h}")
        palette, indices = palette_indices(rgb)
        # graphic control: no disposal, the delay, no transparency
        out += (bytes([_EXTENSION, 0xF9, 4, 0x04]) + struct.pack("<H", frame_delay(fps, index))
                + bytes([0, 0]))
        # image descriptor: the whole screen, a local palette of 256 colours, not interlaced
        out += bytes([_IMAGE]) + struct.pack("<HHHHB", 0, 0, w, h, 0x87) + palette.tobytes()
        out.append(_CODE_BITS)
        out += _sub_blocks(_pack_codes(*_lzw_codes(indices.tobytes())))
    if size is None:
        raise ValueError("a GIF needs at least one frame")
    out.append(_TRAILER)
    return bytes(out)


def write_gif(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> Path:
    """Write an animated GIF atomically (see :func:`encode_gif`)."""
    return atomic_write_bytes(path, encode_gif(frames, fps))


# -- reading ----------------------------------------------------------------------------------
