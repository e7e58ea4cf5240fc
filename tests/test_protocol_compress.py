"""protocol.compress: the three tile layouts are exact, and inflating is always bounded."""

from __future__ import annotations

import tracemalloc
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import ProtocolError
from protocol.compress import ENCODINGS, PALETTE, RAW, SPARSE, pack_cells, unpack_cells


def deflate(data: bytes) -> bytes:
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    return packer.compress(data) + packer.flush()


@st.composite
def tiles(draw):
    h, w = draw(st.integers(1, 128)), draw(st.integers(1, 128))
    k = draw(st.integers(1, 20))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    values = rng.choice(np.arange(-128, 128), k, replace=False).astype(np.int8)
    cells = values[rng.integers(0, k, (h, w))]
    cells[rng.random((h, w)) < draw(st.floats(0, 1))] = 0
    return cells


@settings(max_examples=150, deadline=None)
@given(tiles())
def test_pack_unpack_is_exact(cells):
    encoding, packed = pack_cells(cells)
    assert encoding in ENCODINGS
    assert np.array_equal(unpack_cells(encoding, packed, cells.shape, 0), cells)


def test_each_layout_wins_where_it_should():
    rng = np.random.default_rng(0)
    trinary = rng.choice(np.array([-14, 0, 14], np.int8), (128, 128))
    sparse = np.zeros((128, 128), np.int8)
    sparse[rng.integers(0, 128, 60), rng.integers(0, 128, 60)] = rng.integers(-50, 50, 60)
    sparse[sparse == 0] = 0
    dense = rng.integers(-127, 128, (128, 128)).astype(np.int8)
    assert pack_cells(trinary)[0] == PALETTE
    assert pack_cells(sparse)[0] == SPARSE
    assert pack_cells(dense)[0] == RAW


@settings(max_examples=200)
@given(st.sampled_from((*ENCODINGS, 3, -1)), st.binary(max_size=600), st.integers(1, 40))
def test_arbitrary_streams_raise_protocol_error_only(encoding, data, side):
    try:
        cells = unpack_cells(encoding, data, (side, side), 0)
    except ProtocolError:
        return
    assert cells.shape == (side, side) and cells.dtype == np.int8


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_decompression_bomb_is_refused_for_every_layout(encoding):
    packed = deflate(bytes(10_000_000))  # ~10 KB that would inflate to 10 MB
    tracemalloc.start()
    try:
        with pytest.raises(ProtocolError, match="expands past its bound"):
            unpack_cells(encoding, packed, (256, 256), 4)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000


def test_malformed_palette_tiles():
    def palette(layout: bytes, shape=(2, 4)):
        return unpack_cells(PALETTE, deflate(layout), shape, 7)

    with pytest.raises(ProtocolError, match="palette of 0 values"):
        palette(b"\x00")
    with pytest.raises(ProtocolError, match="palette of 17 values"):
        palette(bytes([17]) + bytes(17))
    with pytest.raises(ProtocolError, match="strictly increasing"):
        palette(bytes([2, 5, 5, 0, 0]))  # 2 values, 1 bit, 1 byte per row
    with pytest.raises(ProtocolError, match="nonzero padding"):
        palette(bytes([2, 1, 5, 0b00001000, 0]))
    with pytest.raises(ProtocolError, match="index beyond its 3 values"):
        palette(bytes([3, 1, 2, 5, 0b11000000, 0]))
    with pytest.raises(ProtocolError, match="palette tile of 4 bytes"):
        palette(bytes([2, 1, 5, 0]))
    with pytest.raises(ProtocolError, match="trailing bytes"):
        unpack_cells(PALETTE, deflate(bytes([1, 5, 0, 0])) + b"xx", (2, 4), 7)


def test_malformed_sparse_tiles():
    def sparse(low: list[int], high: list[int], values: list[int], shape=(2, 4)):
        layout = bytes(low) + bytes(high) + np.array(values, np.int8).tobytes()
        return unpack_cells(SPARSE, deflate(layout), shape, 9)

    with pytest.raises(ProtocolError, match="sparse tile of 2 bytes for 8 cells"):
        unpack_cells(SPARSE, deflate(b"ab"), (2, 4), 9)
    with pytest.raises(ProtocolError, match="expands past its bound of 3 bytes"):
        sparse([0, 1], [0, 0], [1, 1])  # two of eight cells is not < a quarter
    with pytest.raises(ProtocolError, match="repeats a cell"):
        sparse([3, 0], [0, 0], [1, 1], shape=(4, 4))
    with pytest.raises(ProtocolError, match="sparse cell 8 outside the 8-cell tile"):
        sparse([8], [0], [1])
    with pytest.raises(ProtocolError, match="zero value"):
        sparse([0], [0], [0])
    assert sparse([1], [0], [-1]).tolist() == [[0, -1, 0, 0], [0, 0, 0, 0]]
    assert sparse([2, 3], [1, 0], [5, 6], shape=(4, 100))[2, 58:62].tolist() == [5, 0, 0, 6]


def test_sparse_reaches_the_last_cell_of_the_largest_tile():
    cells = np.zeros((256, 256), np.int8)
    cells[-1, -1] = 7
    encoding, packed = pack_cells(cells)
    assert encoding == SPARSE
    assert np.array_equal(unpack_cells(encoding, packed, cells.shape, 0), cells)


def test_truncated_stream_and_unknown_encoding():
    packed = deflate(bytes(64))
    with pytest.raises(ProtocolError, match="truncated"):
        unpack_cells(RAW, packed[:-2], (8, 8), 1)
    with pytest.raises(ProtocolError, match="unknown encoding 5"):
        unpack_cells(5, packed, (8, 8), 1)
