"""Tile cells to byte layouts, layouts to one compressed stream, and back with hard bounds.

Each tile is laid out in the shortest of three byte layouts:

* ``RAW``: the row-major int8 cells.
* ``PALETTE``: up to 16 distinct values, then each cell's palette index packed
  in 1, 2 or 4 bits per cell, rows padded to a byte (PNG's indexed colour).
  Trinary and lightly graded maps shrink by ~12% over RAW.
* ``SPARSE``: for a tile with ``k < n / 4`` nonzero cells of ``n``, the
  row-major gaps between them (the first one counted from cell 0) as uint16, split in
  a plane of low bytes and a plane of high bytes, then their ``k`` values.
  Deltas after one scan are mostly zero: on the intel and freiburg-079
  replays this codes them in ~20% fewer bytes than RAW or a bit mask.

The layouts of all tiles of one message are then compressed as ONE stream, so
that tiles share context (and one stream's overhead), by the codec that gives
the fewest bytes of:

* ``DEFLATE``: raw deflate (zlib, ``wbits=-15``, level 6).
* ``LZMA``: raw LZMA2 (standard-library :mod:`lzma`, no header), literal
  context bits off (``lc=lp=pb=0``: the bytes are packed cells, not text).
  Its repeated-distance matches capture a map's row above, which deflate's
  Huffman-coded distances do not: on real building maps (``bench/protocol.py``) it
  codes a full update in 25-30% fewer bytes than deflate (willow 12.0 ->
  8.5 KB).  It costs ~10 ms of CPU per 100 KB of layout, so it is only tried
  on streams up to :data:`LZMA_MAX_INPUT` bytes (trinary maps of up to ~1M
  cells; a 1000x1000 map of many log-odds levels stays with deflate).
* ``ARITH``: the adaptive arithmetic coder of :mod:`protocol.arith`, for
  messages of SPARSE tiles only (one-scan deltas), up to
  :data:`protocol.arith.MAX_CELLS` cells.

Measured on real maps before picking zlib: see the commit introducing
:mod:`protocol.codec` (zstd saved <3% at level 9, lz4 doubled the size);
LZMA is in the standard library, so it adds no dependency.
"""

from __future__ import annotations

import lzma
import zlib

import numpy as np

from protocol import arith
from protocol.errors import ProtocolError

RAW = 0
PALETTE = 1
SPARSE = 2
ENCODINGS = (RAW, PALETTE, SPARSE)
DEFLATE = 0
LZMA = 1
ARITH = 2
CODECS = (DEFLATE, LZMA, ARITH)
#: zlib level 6: on real maps level 9 saves ~6% more bytes at 5-8x the time.
DEFLATE_LEVEL = 6
MAX_PALETTE = 16
#: Largest stream LZMA is tried on (CPU time grows with the input, ~10 ms per 100 KB).
LZMA_MAX_INPUT = 1 << 18
#: The decoder's dictionary: what a decoder allocates, whatever the sender claims.
LZMA_DICT = 1 << 18
_LZMA_DECODE = [{"id": lzma.FILTER_LZMA2, "dict_size": LZMA_DICT}]
# Hash chains of depth 4 instead of binary trees: ~3x faster on map layouts for
# <0.5% more bytes.
_LZMA_ENCODE = [
    {
        "id": lzma.FILTER_LZMA2,
        "preset": 6,
        "dict_size": LZMA_DICT,
        "lc": 0,
        "lp": 0,
        "pb": 0,
        "mf": lzma.MF_HC4,
        "depth": 4,
    }
]


def _deflate(data: bytes) -> bytes:
    packer = zlib.compressobj(DEFLATE_LEVEL, zlib.DEFLATED, -15)
    return packer.compress(data) + packer.flush()


def _bits_for(k: int) -> int:
    return 1 if k <= 2 else 2 if k <= 4 else 4


def _palette_layout(cells: np.ndarray, values: np.ndarray) -> bytes:
    """``[k][k values][packed indices]`` for a tile with ``k <= 16`` distinct values."""
    bits = _bits_for(len(values))
    per = 8 // bits
    h, w = cells.shape
    lut = np.zeros(256, np.uint8)
    lut[values.view(np.uint8)] = np.arange(len(values), dtype=np.uint8)
    index = np.zeros((h, -(-w // per) * per), np.uint8)
    index[:, :w] = lut[cells.view(np.uint8)]
    groups = index.reshape(h, -1, per)
    packed = np.zeros(groups.shape[:2], np.uint8)
    for i in range(per):
        packed |= groups[:, :, i] << np.uint8(bits * (per - 1 - i))
    return bytes((len(values),)) + values.tobytes() + packed.tobytes()


def _sparse_layout(cells: np.ndarray) -> bytes:
    """``[gap low bytes][gap high bytes][values]`` of the nonzero cells, row-major."""
    flat = cells.ravel()
    where = np.flatnonzero(flat)
    gaps = np.diff(where, prepend=0).astype("<u2")  # < 2**16: tiles hold <= 65536 cells
    return gaps.view(np.uint8).reshape(-1, 2).T.tobytes() + flat[where].tobytes()


def layout_cells(cells: np.ndarray) -> tuple[int, bytes]:
    """``(encoding, layout)``: the shortest layout of an int8 tile, ties to the lower id.

    Chosen by length before compression: deflating every candidate of every
    tile to compare them cost ~7 ms per 1000x1000 map and, once all tiles
    share one stream, picked no smaller streams on real building maps.
    """
    cells = np.ascontiguousarray(cells, dtype=np.int8)
    best = (RAW, cells.tobytes())
    present = np.bincount(cells.view(np.uint8).ravel(), minlength=256) > 0
    if present.sum() <= MAX_PALETTE:
        values = np.flatnonzero(present).astype(np.uint8).view(np.int8)
        values.sort()
        best = (PALETTE, _palette_layout(cells, values))  # at most half of RAW
    # SPARSE is defined for tiles less than a quarter full, where it can win.
    if np.count_nonzero(cells) * 4 < cells.size:
        layout = _sparse_layout(cells)
        if len(layout) < len(best[1]):
            best = (SPARSE, layout)
    return best


def compress(tiles: list[tuple[int, bytes, tuple[int, int]]]) -> tuple[int, bytes]:
    """``(codec, stream)``: the concatenated layouts of ``(encoding, layout, tile shape)``.

    The smallest of deflate, LZMA (inputs up to :data:`LZMA_MAX_INPUT` bytes)
    and the arithmetic coder of :mod:`protocol.arith` (when every layout is
    SPARSE and they hold up to :data:`protocol.arith.MAX_CELLS` cells).
    """
    data = b"".join(layout for _, layout, _ in tiles)
    best = (DEFLATE, _deflate(data))
    if len(data) <= LZMA_MAX_INPUT:
        stream = lzma.compress(data, format=lzma.FORMAT_RAW, filters=_LZMA_ENCODE)
        if len(stream) < len(best[1]):
            best = (LZMA, stream)
    if all(e == SPARSE for e, _, _ in tiles) and len(data) // 3 <= arith.MAX_CELLS:
        stream = arith.encode_sparse([(layout, shape) for _, layout, shape in tiles])
        if len(stream) < len(best[1]):
            best = (ARITH, stream)
    return best


def decompress(codec: int, stream: bytes, tiles: list[tuple[int, int, tuple[int, int]]]) -> bytes:
    """The concatenated layouts ``stream`` holds, given each ``(encoding, size, tile shape)``.

    Never produces more bytes than the sizes add up to.

    Raises
    ------
    ProtocolError
        Unknown codec, a corrupted or truncated stream, trailing bytes, or a
        stream that decompresses to more or fewer bytes than the sizes say.
    """
    size = sum(n for _, n, _ in tiles)
    if codec == ARITH:
        if any(e != SPARSE for e, _, _ in tiles):
            raise ProtocolError("the arithmetic coder carries sparse tiles only", reason="schema")
        return arith.decode_sparse(stream, [(n, shape) for _, n, shape in tiles])
    if codec == DEFLATE:
        unpacker = zlib.decompressobj(-15)
        errors: tuple[type[Exception], ...] = (zlib.error,)
    elif codec == LZMA:
        unpacker = lzma.LZMADecompressor(format=lzma.FORMAT_RAW, filters=_LZMA_DECODE)
        errors = (lzma.LZMAError,)
    else:
        raise ProtocolError(f"unknown compression codec {codec!r}", reason="schema")
    try:
        # One byte beyond the bound proves the stream goes on past it (and a
        # bound of 0 must not become zlib's "no limit").
        out = unpacker.decompress(stream, size + 1)
    except errors as exc:
        raise ProtocolError(f"corrupted stream ({exc})", reason="framing") from None
    if len(out) > size:
        raise ProtocolError(f"stream expands past its bound of {size} bytes", reason="limit")
    if not unpacker.eof:
        raise ProtocolError("compressed stream is truncated", reason="framing")
    if unpacker.unused_data:
        raise ProtocolError("trailing bytes after the compressed stream", reason="framing")
    if len(out) != size:
        raise ProtocolError(
            f"stream decompresses to {len(out)} bytes, the tiles need {size}", reason="value"
        )
    return out


def layout_bound(encoding: int, shape: tuple[int, int], index: int) -> int:
    """Largest layout of ``encoding`` for a tile of ``shape``.

    Raises
    ------
    ProtocolError
        If ``encoding`` is not one of :data:`ENCODINGS`.
    """
    h, w = shape
    n = h * w
    if encoding == RAW:
        return n
    if encoding == PALETTE:
        return 1 + MAX_PALETTE + h * -(-w // 2)
    if encoding == SPARSE:
        return 3 * ((n - 1) // 4)  # 3 bytes for each of < n/4 cells
    raise ProtocolError(f"tile {index}: unknown encoding {encoding!r}", reason="schema")


def _unpack_palette(data: bytes, shape: tuple[int, int], index: int) -> np.ndarray:
    h, w = shape
    k = data[0] if data else 0
    if not 1 <= k <= MAX_PALETTE:
        raise ProtocolError(
            f"tile {index}: palette of {k} values outside 1..{MAX_PALETTE}", reason="value"
        )
    bits = _bits_for(k)
    per = 8 // bits
    row_bytes = -(-w // per)
    if len(data) != 1 + k + h * row_bytes:
        raise ProtocolError(
            f"tile {index}: palette tile of {len(data)} bytes, shape {shape}", reason="value"
        )
    values = np.frombuffer(data, np.int8, k, 1)
    if k > 1 and not (np.diff(values.astype(np.int16)) > 0).all():
        raise ProtocolError(
            f"tile {index}: palette values must be strictly increasing", reason="value"
        )
    packed = np.frombuffer(data, np.uint8, offset=1 + k).reshape(h, row_bytes)
    mask = np.uint8((1 << bits) - 1)
    groups = np.stack(
        [(packed >> np.uint8(bits * (per - 1 - i))) & mask for i in range(per)], axis=-1
    ).reshape(h, row_bytes * per)
    if groups[:, w:].any():
        raise ProtocolError(f"tile {index}: nonzero padding in a palette tile", reason="value")
    idx = groups[:, :w]
    if idx.max(initial=0) >= k:
        raise ProtocolError(f"tile {index}: palette index beyond its {k} values", reason="value")
    return values[idx]


def _unpack_sparse(data: bytes, shape: tuple[int, int], index: int) -> np.ndarray:
    n = shape[0] * shape[1]
    k, rest = divmod(len(data), 3)  # k < n / 4 is enforced by layout_bound
    if rest:
        raise ProtocolError(
            f"tile {index}: sparse tile of {len(data)} bytes for {n} cells", reason="value"
        )
    raw = np.frombuffer(data, np.uint8)
    gaps = raw[:k].astype(np.int64) | (raw[k : 2 * k].astype(np.int64) << 8)
    if k > 1 and gaps[1:].min() < 1:
        raise ProtocolError(f"tile {index}: sparse tile repeats a cell", reason="value")
    where = np.cumsum(gaps)
    if k and where[-1] >= n:
        raise ProtocolError(
            f"tile {index}: sparse cell {where[-1]} outside the {n}-cell tile", reason="value"
        )
    values = raw[2 * k :].view(np.int8)
    if not values.all():
        raise ProtocolError(f"tile {index}: zero value listed in a sparse tile", reason="value")
    cells = np.zeros(n, np.int8)
    cells[where] = values
    return cells.reshape(shape)


def unpack_layout(encoding: int, data: bytes, shape: tuple[int, int], index: int) -> np.ndarray:
    """Inverse of :func:`layout_cells`: the int8 cells of tile ``index`` of ``shape``.

    Raises
    ------
    ProtocolError
        Unknown encoding, a layout longer than :func:`layout_bound`, or one
        that does not match ``shape``.
    """
    if len(data) > layout_bound(encoding, shape, index):
        raise ProtocolError(
            f"tile {index}: layout of {len(data)} bytes exceeds its bound", reason="limit"
        )
    if encoding == RAW:
        if len(data) != shape[0] * shape[1]:
            raise ProtocolError(
                f"tile {index}: raw tile of {len(data)} bytes, shape {shape}", reason="value"
            )
        return np.frombuffer(data, np.int8).reshape(shape)
    if encoding == PALETTE:
        return _unpack_palette(data, shape, index)
    return _unpack_sparse(data, shape, index)
