"""Sun raster codec (DECK.md §5): OpenImageIO has no Sun raster support, so it is ours.

Writes the standard form (depth 24, type 1, pixels B,G,R, rows padded to an even byte
count) and reads depth 1/8/24/32, types 0/1 (BGR, XBGR), 2 (RLE) and 3 (RGB, XRGB),
with or without an RGB colour map. `assignment_order=True` uses the assignment's literal
R,G,B order under type 1/2 instead, for files that must match its code byte for byte.

Reading never trusts the header: sizes are checked against the bytes the file holds
before anything is allocated, and run-length data that would expand past the declared
size is an error, not a big allocation.
"""

from __future__ import annotations

import os
import re
import struct

import numpy as np

from rtjax.atomic import atomic_write
from rtjax.errors import ImageError, writing

__all__ = [
    "SUN_EXTENSIONS",
    "SUN_MAGIC",
    "decode_sunraster",
    "encode_sunraster",
    "is_sunraster_path",
    "read_sunraster",
    "write_sunraster",
]

SUN_MAGIC = 0x59A66A95
SUN_EXTENSIONS = (".sunimg", ".ras", ".sun", ".rs", ".im24", ".im8", ".im1", ".im32")
MAX_PIXELS = 2**28  # a header claiming more than this is absurd, whatever the file holds

_HEADER = struct.Struct(">8I")
RT_OLD, RT_STANDARD, RT_BYTE_ENCODED, RT_FORMAT_RGB = 0, 1, 2, 3
RMT_NONE, RMT_EQUAL_RGB = 0, 1
_RLE_ESC = 0x80
# One RLE token that is not a plain literal byte: 0x80 0x00 (a literal 0x80) or 0x80 n v.
# A regex scans left to right taking non-overlapping matches, which is exactly the
# greedy tokeniser, and it runs in C.
_RLE_TOKEN = re.compile(rb"(\x80\x00|\x80[\x01-\xff][\x00-\xff])", re.DOTALL)


def is_sunraster_path(path: str | os.PathLike) -> bool:
    """True when `path` ends in a Sun raster extension (case-insensitive)."""
    return os.fspath(path).lower().endswith(SUN_EXTENSIONS)


def _row_bytes(width: int, depth: int) -> int:
    """Bytes of one row, padded to an even count (rasterfile.h: rows are 16-bit aligned)."""
    raw = (width * depth + 7) // 8
    return raw + (raw & 1)


def encode_sunraster(image: np.ndarray, *, assignment_order: bool = False) -> bytes:
    """Encode an (H, W, 3) uint8 RGB image as a depth-24, type-1 Sun raster file.

    Pixels are stored B,G,R (the standard that Pillow, xv and netpbm read), or R,G,B
    with `assignment_order=True`. length = padded row bytes × height.
    """
    arr = np.asarray(image)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ImageError(f"cannot encode a Sun raster from a {arr.dtype} array of shape {arr.shape}; expected (H, W, 3) uint8")
    height, width = int(arr.shape[0]), int(arr.shape[1])
    pixels = arr if assignment_order else arr[:, :, ::-1]
    rows = pixels.reshape(height, width * 3)
    row_bytes = _row_bytes(width, 24)
    if row_bytes != width * 3:
        rows = np.concatenate([rows, np.zeros((height, row_bytes - width * 3), np.uint8)], axis=1)
    header = _HEADER.pack(SUN_MAGIC, width, height, 24, row_bytes * height, RT_STANDARD, RMT_NONE, 0)
    return header + np.ascontiguousarray(rows).tobytes()


def decode_sunraster(data: bytes, *, assignment_order: bool = False, source: str = "<bytes>") -> np.ndarray:
    """Decode a Sun raster file's bytes to an (H, W, 3) uint8 RGB array.

    Errors (ImageError, message starting with `source`): bad magic, truncation, an
    unsupported depth/type/maptype, absurd sizes, RLE data that does not decode to
    exactly the declared size, colour-map indices past the map.
    """
    data = bytes(data)
    if len(data) < _HEADER.size:
        raise ImageError(f"{source}: truncated: {len(data)} bytes, a Sun raster header needs {_HEADER.size}")
    magic, width, height, depth, length, rtype, maptype, maplength = _HEADER.unpack_from(data)
    if magic != SUN_MAGIC:
        raise ImageError(f"{source}: not a Sun raster file (magic 0x{magic:08x}, expected 0x{SUN_MAGIC:08x})")
    if depth not in (1, 8, 24, 32):
        raise ImageError(f"{source}: unsupported Sun raster depth {depth} (supported: 1, 8, 24, 32)")
    if rtype not in (RT_OLD, RT_STANDARD, RT_BYTE_ENCODED, RT_FORMAT_RGB):
        raise ImageError(f"{source}: unsupported Sun raster type {rtype} (supported: 0, 1, 2 RLE, 3 RGB)")
    if maptype not in (RMT_NONE, RMT_EQUAL_RGB):
        raise ImageError(f"{source}: unsupported Sun raster colour map type {maptype} (supported: 0 none, 1 RGB)")
    if width < 1 or height < 1 or width * height > MAX_PIXELS:
        raise ImageError(f"{source}: absurd Sun raster size {width}x{height}")

    pos = _HEADER.size
    if maplength > len(data) - pos:
        raise ImageError(f"{source}: truncated: header says a {maplength}-byte colour map, file holds {len(data) - pos}")
    cmap = _colour_map(data[pos : pos + maplength], maptype, depth, source)
    pos += maplength

    row_bytes = _row_bytes(width, depth)
    need = row_bytes * height
    what = f"{width}x{height} {depth}-bit pixels ({need} bytes)"
    avail = len(data) - pos
    if length > avail:
        raise ImageError(f"{source}: truncated: header says {length} bytes of pixel data, file holds {avail}")
    if rtype == RT_BYTE_ENCODED:
        encoded = data[pos : pos + length] if length else data[pos:]
        raw = _rle_decode(encoded, need, what, source)
    else:
        # Tolerate a missing pad byte after the last row; anything less is truncation.
        if avail < need - (row_bytes - (width * depth + 7) // 8):
            raise ImageError(f"{source}: truncated: header says {what}, file holds {avail}")
        raw = data[pos : pos + need]
        raw += bytes(need - len(raw))
    rows = np.frombuffer(raw, np.uint8).reshape(height, row_bytes)
    rgb_order = rtype == RT_FORMAT_RGB or assignment_order
    return _pixels(rows, width, depth, cmap, rgb_order, source)


def _colour_map(raw: bytes, maptype: int, depth: int, source: str) -> np.ndarray | None:
    """The (n, 3) uint8 RGB map of an RMT_EQUAL_RGB file (planes R[], G[], B[]), else None."""
    if maptype != RMT_EQUAL_RGB or depth > 8:
        return None  # no map, or a map that a true-colour image does not use: skipped
    if len(raw) == 0 or len(raw) % 3 or len(raw) > 3 * 256:
        raise ImageError(f"{source}: bad colour map length {len(raw)} (must be 3 × 1..256 entries)")
    return np.frombuffer(raw, np.uint8).reshape(3, -1).T


def _rle_decode(encoded: bytes, need: int, what: str, source: str) -> bytes:
    """Expand type-2 run-length data (0x80 0x00 = literal 0x80; 0x80 n v = n+1 × v).

    Vectorised: the regex finds the escape tokens, numpy repeats each byte by its
    count. The expanded size is known before anything that big is allocated.
    """
    if need > (len(encoded) // 3 + 1) * 256:  # 3 encoded bytes expand to at most 256
        raise ImageError(f"{source}: truncated: {len(encoded)} bytes of RLE data cannot hold {what}")
    parts = _RLE_TOKEN.split(encoded)
    literals, escapes = parts[0::2], parts[1::2]
    if _RLE_ESC in literals[-1]:
        raise ImageError(f"{source}: truncated: RLE data ends inside a run")
    src = np.frombuffer(encoded, np.uint8)
    counts = np.ones(len(src), np.int32)  # at most 256 each
    if escapes:
        lit_len = np.fromiter(map(len, literals[:-1]), np.int64, len(escapes))
        esc_len = np.fromiter(map(len, escapes), np.int64, len(escapes))
        starts = np.cumsum(lit_len) + np.concatenate([[0], np.cumsum(esc_len)[:-1]])
        run = esc_len == 3
        counts[starts] = np.where(run, src[starts + 1].astype(np.int32) + 1, 1)
        counts[starts + 1] = 0
        counts[starts[run] + 2] = 0
        values = src.copy()
        values[starts] = np.where(run, src[np.minimum(starts + 2, len(src) - 1)], _RLE_ESC)
    else:
        values = src
    total = int(counts.sum(dtype=np.int64))
    if total > need:
        raise ImageError(f"{source}: RLE data expands to {total} bytes, past the declared {what}")
    if total < need:
        raise ImageError(f"{source}: truncated: RLE data decodes to {total} bytes, header says {what}")
    return np.repeat(values, counts).tobytes()


def _pixels(rows: np.ndarray, width: int, depth: int, cmap: np.ndarray | None, rgb_order: bool, source: str) -> np.ndarray:
    """Turn padded raw rows into an (H, W, 3) uint8 RGB array."""
    if depth in (24, 32):
        nc = depth // 8
        px = rows[:, : width * nc].reshape(rows.shape[0], width, nc)[:, :, nc - 3 :]  # drop the X byte
        return np.ascontiguousarray(px if rgb_order else px[:, :, ::-1])
    if depth == 8:
        index = rows[:, :width]
    else:  # depth 1: most significant bit first
        index = np.unpackbits(rows, axis=1)[:, :width]
    if cmap is None:
        grey = index if depth == 8 else (1 - index) * np.uint8(255)  # 1 = black
        return np.repeat(grey[:, :, None], 3, axis=2)
    top = int(index.max())
    if top >= len(cmap):
        raise ImageError(f"{source}: pixel index {top} is past the {len(cmap)}-entry colour map")
    return cmap[index]


def read_sunraster(path: str | os.PathLike, *, assignment_order: bool = False) -> np.ndarray:
    """Read a Sun raster file as (H, W, 3) uint8 RGB; ImageError on any problem."""
    name = os.fspath(path)
    try:
        with open(name, "rb") as f:
            data = f.read()
    except (OSError, ValueError) as e:  # ValueError: a name with a NUL byte
        raise ImageError(f"{name}: cannot read: {getattr(e, 'strerror', None) or e}") from e
    return decode_sunraster(data, assignment_order=assignment_order, source=name)


def write_sunraster(path: str | os.PathLike, image: np.ndarray, *, assignment_order: bool = False) -> None:
    """Write an (H, W, 3) uint8 image as a Sun raster file, atomically."""
    name = os.fspath(path)
    data = encode_sunraster(image, assignment_order=assignment_order)
    with writing(name, ImageError):
        atomic_write(name, data)
