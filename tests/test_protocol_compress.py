"""protocol.compress and protocol.arith: layouts and codecs are exact, decoding is bounded."""

from __future__ import annotations

import lzma
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from refusals import refused, refused_within

from protocol import ProtocolError, arith
from protocol.compress import (
    ARITH,
    CODECS,
    DEFLATE,
    ENCODINGS,
    LZMA,
    PALETTE,
    RAW,
    SPARSE,
    compress,
    decompress,
    layout_cells,
    unpack_layout,
)


@st.composite
def tiles(draw, max_side=128):
    h, w = draw(st.integers(1, max_side)), draw(st.integers(1, max_side))
    k = draw(st.integers(1, 20))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    values = rng.choice(np.arange(-128, 128), k, replace=False).astype(np.int8)
    cells = values[rng.integers(0, k, (h, w))]
    cells[rng.random((h, w)) < draw(st.floats(0, 1))] = 0
    return cells


def round_trip(cells_list: list[np.ndarray]) -> tuple[int, list[np.ndarray]]:
    laid = [(*layout_cells(c), c.shape) for c in cells_list]
    codec, stream = compress(laid)
    data = decompress(codec, stream, [(e, len(b), shape) for e, b, shape in laid])
    out, at = [], 0
    for (e, b, _), c in zip(laid, cells_list, strict=True):
        out.append(unpack_layout(e, data[at : at + len(b)], c.shape, 0))
        at += len(b)
    return codec, out


@settings(max_examples=150)
@given(st.lists(tiles(), min_size=1, max_size=3))
def test_layouts_and_codecs_are_exact(cells_list):
    codec, out = round_trip(cells_list)
    assert codec in CODECS
    assert all(np.array_equal(a, b) for a, b in zip(out, cells_list, strict=True))


@settings(max_examples=100)
@given(st.lists(tiles(max_side=40), min_size=1, max_size=4), st.integers(0, 2**32 - 1))
def test_arithmetic_coder_is_exact_on_sparse_layouts(cells_list, seed):
    rng = np.random.default_rng(seed)
    sparse = []
    for cells in cells_list:
        cells = cells.copy()
        cells[rng.random(cells.shape) < 0.8] = 0
        sparse.append(cells)
    tiles = [
        (b, c.shape) for b, c in zip(map(_sparse, sparse), sparse, strict=True) if b is not None
    ]
    if not tiles or sum(len(b) for b, _ in tiles) // 3 > arith.MAX_CELLS:
        return
    stream = arith.encode_sparse(tiles)
    assert not stream.endswith(b"\x00")
    sizes = [(len(b), shape) for b, shape in tiles]
    assert arith.decode_sparse(stream, sizes) == b"".join(b for b, _ in tiles)


def _sparse(cells: np.ndarray) -> bytes | None:
    """The SPARSE layout of ``cells`` if they are less than a quarter full."""
    if np.count_nonzero(cells) * 4 >= cells.size:
        return None
    flat = cells.ravel()
    where = np.flatnonzero(flat)
    gaps = np.diff(where, prepend=0).astype("<u2")
    return gaps.view(np.uint8).reshape(-1, 2).T.tobytes() + flat[where].tobytes()


def test_each_layout_wins_where_it_should():
    rng = np.random.default_rng(0)
    trinary = rng.choice(np.array([-14, 0, 14], np.int8), (128, 128))
    sparse = np.zeros((128, 128), np.int8)
    sparse[rng.integers(0, 128, 60), rng.integers(0, 128, 60)] = rng.integers(-50, 50, 60)
    dense = rng.integers(-127, 128, (128, 128)).astype(np.int8)
    assert layout_cells(trinary)[0] == PALETTE
    assert layout_cells(sparse)[0] == SPARSE
    assert layout_cells(dense)[0] == RAW


@settings(max_examples=200)
@given(
    st.sampled_from((*CODECS, 3, -1)),
    st.binary(max_size=600),
    st.lists(
        st.tuples(
            st.sampled_from((*ENCODINGS, 7)),
            st.integers(0, 700),
            st.tuples(st.integers(1, 40), st.integers(1, 40)),
        ),
        max_size=3,
    ),
)
def test_arbitrary_streams_raise_protocol_error_only(codec, data, layouts):
    try:
        out = decompress(codec, data, layouts)
    except ProtocolError:
        return
    assert len(out) == sum(n for _, n, _ in layouts)


@settings(max_examples=200)
@given(st.sampled_from((*ENCODINGS, 3, -1)), st.binary(max_size=600), st.integers(1, 40))
def test_arbitrary_layouts_raise_protocol_error_only(encoding, data, side):
    try:
        cells = unpack_layout(encoding, data, (side, side), 0)
    except ProtocolError:
        return
    assert cells.shape == (side, side) and cells.dtype == np.int8


def deflate(data: bytes) -> bytes:
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    return packer.compress(data) + packer.flush()


def _lzma(data: bytes) -> bytes:
    filters = [{"id": lzma.FILTER_LZMA2, "dict_size": 1 << 18}]
    return lzma.compress(data, format=lzma.FORMAT_RAW, filters=filters)


@pytest.mark.parametrize(("codec", "pack"), [(DEFLATE, deflate), (LZMA, _lzma)])
def test_decompression_bomb_is_refused_for_every_codec(codec, pack):
    packed = pack(bytes(10_000_000))  # ~10 KB that would decompress to 10 MB
    assert len(packed) < 12_000
    with refused_within("limit", "expands past its bound of 65536 bytes", 1_000_000):
        decompress(codec, packed, [(RAW, 65536, (256, 256))])


def test_arithmetic_coder_work_is_bounded():
    cells = arith.MAX_CELLS + 1
    with refused("limit", f"more than {arith.MAX_CELLS} cells"):
        decompress(ARITH, b"\x01" * 100, [(SPARSE, 3 * cells, (256, 256))])
    with refused("framing", "sparse layouts of 3 bytes per cell"):
        decompress(ARITH, b"\x01" * 100, [(SPARSE, 4, (8, 8))])
    with refused("schema", "sparse tiles only"):
        decompress(ARITH, b"\x01" * 100, [(RAW, 3, (1, 3))])
    with refused("limit", "number longer than a tile side"):
        decompress(ARITH, b"\xff" * 8, [(SPARSE, 3, (4, 4))])
    cells = np.zeros((16, 16), np.int8)
    cells[10, 3] = 5
    stream = arith.encode_sparse([(_sparse(cells), (16, 16))])
    with refused("value", r"cell \(10, 3\) outside its 4x4 tile"):
        decompress(ARITH, stream, [(SPARSE, 3, (4, 4))])


def test_arithmetic_stream_must_end_with_its_last_cell():
    cells = np.zeros((16, 16), np.int8)
    cells[[1, 5, 9], [2, 3, 4]] = [-3, -2, 6]
    layout = _sparse(cells)
    tiles = [(SPARSE, len(layout), (16, 16))]
    stream = arith.encode_sparse([(layout, (16, 16))])
    assert decompress(ARITH, stream, tiles) == layout
    with refused("framing", "ends at byte"):
        decompress(ARITH, stream + b"\x07" * 5, tiles)
    with refused("framing", "ends in a zero byte"):
        decompress(ARITH, stream + b"\x00", tiles)


def test_malformed_palette_tiles():
    def palette(layout: bytes, shape=(2, 4)):
        return unpack_layout(PALETTE, layout, shape, 7)

    with refused("value", "palette of 0 values"):
        palette(b"\x00")
    with refused("value", "palette of 17 values"):
        palette(bytes([17]) + bytes(7))
    with refused("value", "strictly increasing"):
        palette(bytes([2, 5, 5, 0, 0]))  # 2 values, 1 bit, 1 byte per row
    with refused("value", "nonzero padding"):
        palette(bytes([2, 1, 5, 0b00001000, 0]))
    with refused("value", "index beyond its 3 values"):
        palette(bytes([3, 1, 2, 5, 0b11000000, 0]))
    with refused("value", "palette tile of 4 bytes"):
        palette(bytes([2, 1, 5, 0]))


def test_malformed_sparse_tiles():
    def sparse(low: list[int], high: list[int], values: list[int], shape=(2, 4)):
        layout = bytes(low) + bytes(high) + np.array(values, np.int8).tobytes()
        return unpack_layout(SPARSE, layout, shape, 9)

    with refused("value", "sparse tile of 2 bytes for 8 cells"):
        unpack_layout(SPARSE, b"ab", (2, 4), 9)
    with refused("limit", "layout of 6 bytes exceeds its bound"):
        sparse([0, 1], [0, 0], [1, 1])  # two of eight cells is not < a quarter
    with refused("value", "repeats a cell"):
        sparse([3, 0], [0, 0], [1, 1], shape=(4, 4))
    with refused("value", "sparse cell 8 outside the 8-cell tile"):
        sparse([8], [0], [1])
    with refused("value", "zero value"):
        sparse([0], [0], [0])
    assert sparse([1], [0], [-1]).tolist() == [[0, -1, 0, 0], [0, 0, 0, 0]]
    assert sparse([2, 3], [1, 0], [5, 6], shape=(4, 100))[2, 58:62].tolist() == [5, 0, 0, 6]


def test_sparse_reaches_the_last_cell_of_the_largest_tile():
    cells = np.zeros((256, 256), np.int8)
    cells[-1, -1] = 7
    assert np.array_equal(round_trip([cells])[1][0], cells)
    layout = layout_cells(cells)[1]
    assert layout_cells(cells)[0] == SPARSE
    stream = arith.encode_sparse([(layout, cells.shape)])
    assert decompress(ARITH, stream, [(SPARSE, len(layout), cells.shape)]) == layout


def test_truncated_stream_unknown_encoding_and_codec():
    for codec, pack in ((DEFLATE, deflate), (LZMA, _lzma)):
        packed = pack(bytes(64))
        with refused("framing", "truncated"):
            decompress(codec, packed[:-2], [(RAW, 64, (8, 8))])
        with refused("framing", "trailing bytes"):
            decompress(codec, packed + b"xx", [(RAW, 64, (8, 8))])
    with pytest.raises(ProtocolError, match="unknown encoding 5"):
        unpack_layout(5, bytes(64), (8, 8), 1)
    with pytest.raises(ProtocolError, match="unknown compression codec 9"):
        decompress(9, deflate(bytes(64)), [(RAW, 64, (8, 8))])


@settings(max_examples=100)
@given(st.lists(st.tuples(st.integers(0, arith._CONTEXTS - 1), st.booleans()), max_size=3000))
def test_arithmetic_decoder_reads_every_bit_the_encoder_coded(steps):
    """Bit by bit, any context and any run (long runs of one context pass the rescaling):
    the decoder's model is the encoder's."""
    enc = arith._Encoder()
    for ctx, bit in steps:
        enc.bit(ctx, int(bit))
    dec = arith._Decoder(enc.finish())
    assert [dec.bit(ctx) for ctx, _ in steps] == [int(bit) for _, bit in steps]
    dec.finish()
    assert (dec.zeros, dec.ones) == (enc.zeros, enc.ones)
