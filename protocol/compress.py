"""Tile cells to compressed bytes and back, with a hard bound on what inflating may produce.

Three encodings, all raw deflate (zlib, ``wbits=-15``, level 6) of a
different byte layout; the encoder keeps whichever is smallest per tile:

* ``RAW``: the row-major int8 cells.
* ``PALETTE``: up to 16 distinct values, then each cell's palette index packed
  in 1, 2 or 4 bits per cell, rows padded to a byte (PNG's indexed colour).
  Trinary and lightly graded maps shrink by ~12% over RAW.
* ``SPARSE``: for a tile with ``k < n / 4`` nonzero cells of ``n``, the
  row-major gaps between them (the first one counted from cell 0) as uint16, split in
  a plane of low bytes and a plane of high bytes, then their ``k`` values.
  Deltas after one scan are mostly zero: on the intel and freiburg-079
  replays this codes them in ~20% fewer bytes than RAW or a bit mask.

Measured on real maps before picking zlib: see the commit introducing
:mod:`protocol.codec` (zstd saved <3% at level 9, lz4 doubled the size).
"""

from __future__ import annotations

import zlib

import numpy as np

from protocol.errors import ProtocolError

RAW = 0
PALETTE = 1
SPARSE = 2
ENCODINGS = (RAW, PALETTE, SPARSE)
#: zlib level 6: on real maps level 9 saves ~6% more bytes at 5-8x the time.
DEFLATE_LEVEL = 6
MAX_PALETTE = 16


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


def pack_cells(cells: np.ndarray) -> tuple[int, bytes]:
    """The smallest ``(encoding, deflated bytes)`` of an int8 tile; ties go to the lower id."""
    cells = np.ascontiguousarray(cells, dtype=np.int8)
    best = (RAW, _deflate(cells.data))
    present = np.bincount(cells.view(np.uint8).ravel(), minlength=256) > 0
    if present.sum() <= MAX_PALETTE:
        values = np.flatnonzero(present).astype(np.uint8).view(np.int8)
        values.sort()
        candidate = _deflate(_palette_layout(cells, values))
        if len(candidate) < len(best[1]):
            best = (PALETTE, candidate)
    # SPARSE is defined for tiles less than a quarter full, where it can win.
    if np.count_nonzero(cells) * 4 < cells.size:
        candidate = _deflate(_sparse_layout(cells))
        if len(candidate) < len(best[1]):
            best = (SPARSE, candidate)
    return best


def _inflate(packed: bytes, bound: int, index: int) -> bytes:
    """Raw-inflate ``packed``, refusing to produce more than ``bound`` bytes."""
    inflater = zlib.decompressobj(-15)
    try:
        out = inflater.decompress(packed, bound)
        # Output stopped at the bound: one more byte proves the stream goes on,
        # none means it ends here (its final bits were merely not consumed yet).
        if not inflater.eof and inflater.decompress(inflater.unconsumed_tail, 1):
            raise ProtocolError(f"tile {index}: expands past its bound of {bound} bytes")
    except zlib.error as exc:
        raise ProtocolError(f"tile {index}: corrupted deflate stream ({exc})") from None
    if not inflater.eof:
        raise ProtocolError(f"tile {index}: deflate stream is truncated")
    if inflater.unused_data:
        raise ProtocolError(f"tile {index}: trailing bytes after the deflate stream")
    return out


def _unpack_palette(data: bytes, shape: tuple[int, int], index: int) -> np.ndarray:
    h, w = shape
    k = data[0] if data else 0
    if not 1 <= k <= MAX_PALETTE:
        raise ProtocolError(f"tile {index}: palette of {k} values outside 1..{MAX_PALETTE}")
    bits = _bits_for(k)
    per = 8 // bits
    row_bytes = -(-w // per)
    if len(data) != 1 + k + h * row_bytes:
        raise ProtocolError(f"tile {index}: palette tile of {len(data)} bytes, shape {shape}")
    values = np.frombuffer(data, np.int8, k, 1)
    if k > 1 and not (np.diff(values.astype(np.int16)) > 0).all():
        raise ProtocolError(f"tile {index}: palette values must be strictly increasing")
    packed = np.frombuffer(data, np.uint8, offset=1 + k).reshape(h, row_bytes)
    mask = np.uint8((1 << bits) - 1)
    groups = np.stack(
        [(packed >> np.uint8(bits * (per - 1 - i))) & mask for i in range(per)], axis=-1
    ).reshape(h, row_bytes * per)
    if groups[:, w:].any():
        raise ProtocolError(f"tile {index}: nonzero padding in a palette tile")
    idx = groups[:, :w]
    if idx.max(initial=0) >= k:
        raise ProtocolError(f"tile {index}: palette index beyond its {k} values")
    return values[idx]


def _sparse_bound(n: int) -> int:
    """Largest SPARSE layout of an ``n``-cell tile: 3 bytes for each of < n/4 cells."""
    return 3 * ((n - 1) // 4)


def _unpack_sparse(data: bytes, shape: tuple[int, int], index: int) -> np.ndarray:
    n = shape[0] * shape[1]
    k, rest = divmod(len(data), 3)  # k < n / 4 is enforced by the inflate bound
    if rest:
        raise ProtocolError(f"tile {index}: sparse tile of {len(data)} bytes for {n} cells")
    raw = np.frombuffer(data, np.uint8)
    gaps = raw[:k].astype(np.int64) | (raw[k : 2 * k].astype(np.int64) << 8)
    if k > 1 and gaps[1:].min() < 1:
        raise ProtocolError(f"tile {index}: sparse tile repeats a cell")
    where = np.cumsum(gaps)
    if k and where[-1] >= n:
        raise ProtocolError(f"tile {index}: sparse cell {where[-1]} outside the {n}-cell tile")
    values = raw[2 * k :].view(np.int8)
    if not values.all():
        raise ProtocolError(f"tile {index}: zero value listed in a sparse tile")
    cells = np.zeros(n, np.int8)
    cells[where] = values
    return cells.reshape(shape)


def unpack_cells(encoding: int, packed: bytes, shape: tuple[int, int], index: int) -> np.ndarray:
    """Inverse of :func:`pack_cells` for a tile of ``shape``; never inflates past the tile's bound.

    Raises
    ------
    ProtocolError
        Unknown encoding, corrupted or oversized stream, or a layout that does
        not match ``shape``.
    """
    h, w = shape
    n = h * w
    if encoding == RAW:
        data = _inflate(packed, n, index)
        if len(data) != n:
            raise ProtocolError(f"tile {index}: inflates to {len(data)} bytes, expected {n}")
        return np.frombuffer(data, np.int8).reshape(shape)
    if encoding == PALETTE:
        bound = 1 + MAX_PALETTE + h * -(-w // 2)
        return _unpack_palette(_inflate(packed, bound, index), shape, index)
    if encoding == SPARSE:
        return _unpack_sparse(_inflate(packed, _sparse_bound(n), index), shape, index)
    raise ProtocolError(f"tile {index}: unknown encoding {encoding!r}")
