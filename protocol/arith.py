"""An adaptive binary range coder for the sparse cells of small deltas.

A one-scan delta changes a few hundred cells.  Deflate then spends a good part
of the stream on its Huffman tables and whole bits per symbol; this coder
needs no table and spends fractions of a bit, and on the intel and
freiburg-079 replays it codes one-scan deltas in ~15-20% fewer bytes.

What is coded is a list of SPARSE tile layouts (:mod:`protocol.compress`),
each the row-major nonzero cells of one tile, row by row (see
:func:`encode_sparse`): small numbers as Elias-gamma codes (bit length in
unary, then the lower bits, the top two with a context per length and
position), values as the 8 bits of their byte down an adaptive binary tree.

The probabilities start uniform and follow the counts seen so far
(Krichevsky-Trofimov), one model shared by all tiles of the message.  The
range coder is LZMA's (32-bit range, carries through a cached byte).  Pure
Python, about 10 decisions per cell, so :data:`MAX_CELLS` bounds what a
message may ask a decoder to do.
"""

from __future__ import annotations

import numpy as np

from protocol.errors import ProtocolError
from protocol.messages import TILE_SIZES

#: Cells one stream may hold: a decoder's work is ~10 us per cell in pure Python, so a
#: hostile message costs at most ~20-40 ms (a one-scan delta holds ~350-700 cells).
MAX_CELLS = 2048
_TOP = 1 << 24
_MASK32 = 0xFFFFFFFF
#: Counts are halved past this total so the model keeps following the data.
_RESCALE = 1 << 12
#: Elias-gamma lengths above this cannot come from a row or column of a tile.
_MAX_LENGTH = max(TILE_SIZES).bit_length()


# Contexts are indices into flat count lists: value-tree nodes 1..255, then a
# block of 64 per kind of number (unary bits, mantissa bits, sign), then the
# two "same row" flags.
_VALUE = 0
_NUMBER = 256
_R0, _C0, _GAP, _ROWS, _COL = (_NUMBER + 64 * k for k in range(5))
_SAME = _NUMBER + 64 * 5
_CONTEXTS = _SAME + 2


def _mantissa(length: int, i: int) -> int:
    """Offset of mantissa bit ``i`` of a ``length``-bit number: the top two bits apart."""
    return 16 + 3 * length + min(length - 1 - i, 2)


class _Coder:
    """Adaptive bit probabilities by context: counts of zeros and ones, doubled, from 1 each."""

    def __init__(self) -> None:
        self.zeros = [1] * _CONTEXTS
        self.ones = [1] * _CONTEXTS
        self.range = _MASK32

    def bound(self, ctx: int) -> int:
        """Where the range splits for ``ctx``: P(0) = zeros / (zeros + ones), 11 bits, >= 1/2048."""
        z = self.zeros[ctx]
        return (self.range >> 11) * max((z << 11) // (z + self.ones[ctx]), 1)

    def learn(self, ctx: int, bit: int) -> None:
        z, o = self.zeros[ctx], self.ones[ctx]
        if bit:
            o += 2
        else:
            z += 2
        if z + o > _RESCALE:
            z, o = (z + 1) >> 1, (o + 1) >> 1
        self.zeros[ctx], self.ones[ctx] = z, o


class _Encoder(_Coder):
    def __init__(self) -> None:
        super().__init__()
        self.low, self.range, self.cache, self.pending = 0, _MASK32, 0, 1
        self.out = bytearray()

    def bit(self, ctx: int, bit: int) -> None:
        bound = self.bound(ctx)
        self.learn(ctx, bit)
        if bit:
            self.low += bound
            self.range -= bound
        else:
            self.range = bound
        while self.range < _TOP:
            self.range = (self.range << 8) & _MASK32
            self._shift()

    def _shift(self) -> None:
        if self.low < 0xFF000000 or self.low > _MASK32:
            carry = self.low >> 32
            byte = self.cache
            while True:
                self.out.append((byte + carry) & 0xFF)
                byte = 0xFF
                self.pending -= 1
                if not self.pending:
                    break
            self.cache = (self.low >> 24) & 0xFF
        self.pending += 1
        self.low = (self.low & 0x00FFFFFF) << 8

    def finish(self) -> bytes:
        """The coded bytes, without what a decoder can infer.

        The first byte is always 0 and the decoder reads zeros past the end, so
        the final value is rounded up to the roundest number in the current
        interval, whose trailing zero bytes are then dropped.
        """
        for unit in (1 << 32, 1 << 24, 1 << 16, 1 << 8, 1):
            value = -(-self.low // unit) * unit
            if value < self.low + self.range:
                self.low = value
                break
        for _ in range(5):
            self._shift()
        return bytes(self.out[1:]).rstrip(b"\x00")


class _Decoder(_Coder):
    def __init__(self, data: bytes) -> None:
        super().__init__()
        if data.endswith(b"\x00"):
            raise ProtocolError("arithmetic-coded stream ends in a zero byte", reason="framing")
        self.data, self.pos = data, 4
        self.code, self.range = int.from_bytes(data[:4].ljust(4, b"\x00"), "big"), _MASK32

    def bit(self, ctx: int) -> int:
        # bound() and learn() inlined: the receive thread decodes ~10 bits per cell of every
        # delta, and the two calls were half of its time.  Same model, bit for bit (the
        # round-trip property tests hold the encoder, which calls them, to it).
        zeros, ones = self.zeros, self.ones
        z, o = zeros[ctx], ones[ctx]
        rng = self.range
        bound = (rng >> 11) * (((z << 11) // (z + o)) or 1)
        if self.code >= bound:
            bit = 1
            self.code -= bound
            rng -= bound
            o += 2
        else:
            bit = 0
            rng = bound
            z += 2
        if z + o > _RESCALE:
            z, o = (z + 1) >> 1, (o + 1) >> 1
        zeros[ctx], ones[ctx] = z, o
        while rng < _TOP:
            rng = (rng << 8) & _MASK32
            # Past the end the stream reads as zeros; how far is checked in finish().
            byte = self.data[self.pos] if self.pos < len(self.data) else 0
            self.code = ((self.code << 8) | byte) & _MASK32
            self.pos += 1
        self.range = rng
        return bit

    def finish(self) -> None:
        # The decoder reads up to 4 bytes ahead, dropped zeros included; unread
        # bytes would be trailing garbage.
        if self.pos < len(self.data):
            raise ProtocolError(
                f"arithmetic-coded stream of {len(self.data)} bytes ends at byte {self.pos}",
                reason="framing",
            )


def _put_number(enc: _Encoder, ctx: int, n: int) -> None:
    """Elias-gamma of ``n + 1``: its bit length in unary, then its lower bits."""
    n += 1
    length = n.bit_length() - 1
    for i in range(length):
        enc.bit(ctx + i, 1)
    enc.bit(ctx + length, 0)
    for i in range(length - 1, -1, -1):
        enc.bit(ctx + _mantissa(length, i), (n >> i) & 1)


def _get_number(dec: _Decoder, ctx: int) -> int:
    length = 0
    while dec.bit(ctx + length):
        length += 1
        if length > _MAX_LENGTH:
            raise ProtocolError("arithmetic-coded number longer than a tile side", reason="limit")
    n = 1
    for i in range(length - 1, -1, -1):
        n = (n << 1) | dec.bit(ctx + _mantissa(length, i))
    return n - 1


def _put_signed(enc: _Encoder, ctx: int, n: int) -> None:
    _put_number(enc, ctx, abs(n))
    if n:
        enc.bit(ctx + 63, int(n < 0))


def _get_signed(dec: _Decoder, ctx: int) -> int:
    n = _get_number(dec, ctx)
    return -n if n and dec.bit(ctx + 63) else n


def _put_value(enc: _Encoder, value: int) -> None:
    node = 1
    for i in range(7, -1, -1):
        bit = (value >> i) & 1
        enc.bit(_VALUE + node, bit)
        node = (node << 1) | bit


def _get_value(dec: _Decoder) -> int:
    node = 1
    for _ in range(8):
        node = (node << 1) | dec.bit(_VALUE + node)
    return node & 0xFF


def encode_sparse(tiles: list[tuple[bytes, tuple[int, int]]]) -> bytes:
    """Arithmetic-code SPARSE layouts, each given with the shape of its tile.

    A layout is ``[gap low bytes][gap high bytes][values]`` (see
    :mod:`protocol.compress`); the cells are coded row by row: a flag for
    "same row as the previous cell" (in the context of whether the previous
    cell touched its own predecessor), then the columns skipped in that row,
    or else the rows skipped and the column relative to where the previous
    row's cells began (the edges of a scan's fan move little from row to row).
    """
    enc = _Encoder()
    for layout, (_, w) in tiles:
        _code_cells(enc, *_cells(layout, w))
    return enc.finish()


def _code_cells(enc: _Encoder, rows: list[int], cols: list[int], values: list[int]) -> None:
    prev_r = prev_c = start = -1
    touching = False
    for r, c, v in zip(rows, cols, values, strict=True):
        if prev_r < 0:
            _put_number(enc, _R0, r)
            _put_number(enc, _C0, c)
            start = c
        else:
            same = r == prev_r
            enc.bit(_SAME + touching, int(same))
            if same:
                _put_number(enc, _GAP, c - prev_c - 1)
            else:
                _put_number(enc, _ROWS, r - prev_r - 1)
                _put_signed(enc, _COL, c - start)
                start = c
            touching = same and c == prev_c + 1
        _put_value(enc, v)
        prev_r, prev_c = r, c


def decode_sparse(stream: bytes, tiles: list[tuple[int, tuple[int, int]]]) -> bytes:
    """The concatenated SPARSE layouts that ``stream`` codes, given each one's size and shape.

    Raises
    ------
    ProtocolError
        If a size is not a whole number of cells, the cells exceed
        :data:`MAX_CELLS`, a cell falls outside its tile, or the stream is
        malformed or does not end where the last cell does.
    """
    if any(size % 3 for size, _ in tiles):
        raise ProtocolError(
            "arithmetic-coded tiles must be sparse layouts of 3 bytes per cell", reason="framing"
        )
    if sum(size for size, _ in tiles) // 3 > MAX_CELLS:
        raise ProtocolError(
            f"arithmetic-coded stream of more than {MAX_CELLS} cells", reason="limit"
        )
    dec = _Decoder(stream)
    out = []
    for size, (h, w) in tiles:
        k = size // 3
        where = np.empty(k, np.int64)
        values = np.empty(k, np.uint8)
        r = c = start = -1
        touching = False
        for j in range(k):
            if j == 0:
                r = _get_number(dec, _R0)
                c = start = _get_number(dec, _C0)
            elif dec.bit(_SAME + touching):
                skipped = _get_number(dec, _GAP)
                c += skipped + 1
                touching = skipped == 0
            else:
                r += _get_number(dec, _ROWS) + 1
                c = start = start + _get_signed(dec, _COL)
                touching = False
            if not (0 <= c < w and r < h):
                raise ProtocolError(
                    f"arithmetic-coded cell ({r}, {c}) outside its {h}x{w} tile", reason="value"
                )
            where[j] = r * w + c
            values[j] = _get_value(dec)
        gaps = np.diff(where, prepend=0).astype("<u2")
        out.append(gaps.view(np.uint8).reshape(-1, 2).T.tobytes() + values.tobytes())
    dec.finish()
    return b"".join(out)


def _cells(layout: bytes, w: int) -> tuple[list[int], list[int], list[int]]:
    """Rows, columns and value bytes of the cells of a SPARSE layout of a ``w``-wide tile."""
    k = len(layout) // 3
    raw = np.frombuffer(layout, np.uint8)
    where = np.cumsum(raw[:k].astype(np.int64) | (raw[k : 2 * k].astype(np.int64) << 8))
    return (where // w).tolist(), (where % w).tolist(), raw[2 * k :].tolist()
