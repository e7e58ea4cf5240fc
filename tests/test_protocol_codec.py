"""protocol.codec: round trips, and every way a message can be refused."""

from __future__ import annotations

import contextlib
import math
import tracemalloc
import zlib

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import (
    Geometry,
    Heartbeat,
    Limits,
    Link,
    Manifest,
    MapTiles,
    ProtocolError,
    Status,
    Tile,
    decode,
    encode,
)
from protocol.auth import seal
from protocol.codec import MAGIC, SCHEMA_VERSION, encode_tiles
from protocol.tiles import checksum

KEY = b"fleet-key-for-tests-0123456789ab"

ids = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_-]{0,20}", fullmatch=True)
versions = st.integers(0, 2**63 - 1)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
matrices = st.lists(finite, min_size=9, max_size=9).map(lambda v: np.array(v).reshape(3, 3))


def raw(body: dict, key: bytes | None = None, schema: int = SCHEMA_VERSION) -> bytes:
    """A sealed message around a hand-made body, to reach the checks behind the trailer."""
    head = MAGIC + bytes((schema, 1 if key else 0))
    payload = head + msgpack.packb(body, use_bin_type=True)
    return payload + seal(payload, key)


def tile_body(cells: np.ndarray, crc: int | None = None, shape=(20, 30), ts=16) -> dict:
    """A tiles body holding tile 0 (deflated ``cells``) of a map of ``shape``."""
    packer = zlib.compressobj(6, zlib.DEFLATED, -15)
    packed = packer.compress(cells.tobytes()) + packer.flush()
    crc = checksum(cells) if crc is None else crc
    return {
        "k": "tiles",
        "f": "fleet",
        "r": "r1",
        "v": 3,
        "g": [shape[0], shape[1], 0.05, 0.0, 0.0, 0.0, ts],
        "b": None,
        "t": [[0, crc, None, 0, packed]],
    }


def sample_messages() -> list:
    g = Geometry((20, 30), 0.05, (1.0, -2.0, 0.1), 16)
    cells = np.arange(16 * 16, dtype=np.int64).reshape(16, 16).astype(np.int8) % 100
    cells = cells.astype(np.int8)
    return [
        MapTiles("fleet", "r1", 3, g, (Tile(0, checksum(cells), cells),)),
        Manifest("fleet", "r1", 3, g, {0: checksum(cells), 3: 7}),
        Manifest("fleet", "r1", 4, g, {1: 9}, base_version=3, digest=2**64 - 1),
        Link("fleet", "r1", "r1", "r2", 3, 4, True, np.eye(3), np.eye(3) * 0.5, 0.93),
        Heartbeat("fleet", "r1", 17, 3),
        Status("fleet", "r1", 18, {"dropped": 2, "merge_ms": 12.5}),
    ]


@pytest.mark.parametrize("key", [None, KEY])
def test_every_kind_round_trips(key):
    for msg in sample_messages():
        out = decode(encode(msg, key), key)
        assert type(out) is type(msg)
        if isinstance(msg, MapTiles):
            assert (out.fleet, out.robot, out.version, out.geometry) == (
                msg.fleet,
                msg.robot,
                msg.version,
                msg.geometry,
            )
            assert np.array_equal(out.tiles[0].cells, msg.tiles[0].cells)
        else:
            assert out == msg


def test_bytes_like_input_and_non_bytes():
    wire = encode(Heartbeat("f", "r", 1))
    assert decode(bytearray(wire)) == decode(memoryview(wire)) == Heartbeat("f", "r", 1)
    with pytest.raises(ProtocolError, match="message must be bytes, got str"):
        decode("PG")


@given(
    fleet=ids, a=ids, b=ids, va=versions, vb=versions, ok=st.booleans(), m=matrices,
    cov=matrices, score=finite,
)  # fmt: skip
def test_link_round_trips(fleet, a, b, va, vb, ok, m, cov, score):
    if a == b:
        b = a + "x"
    msg = Link(fleet, a, a, b, va, vb, ok, m, cov, score)
    assert decode(encode(msg)) == msg


@given(
    robot=ids,
    seq=versions,
    counters=st.dictionaries(
        st.from_regex(r"[A-Za-z0-9_.-]{1,64}", fullmatch=True),
        st.one_of(st.integers(-(2**63), 2**63 - 1), finite),
        max_size=20,
    ),
)
def test_status_round_trips(robot, seq, counters):
    msg = Status("f", robot, seq, counters)
    assert decode(encode(msg, KEY), KEY) == msg


@settings(suppress_health_check=[HealthCheck.too_slow], max_examples=300)
@given(st.binary(max_size=2000))
def test_random_bytes_raise_protocol_error_only(data):
    for key in (None, KEY):
        with pytest.raises(ProtocolError):
            decode(data, key)


@settings(max_examples=300)
@given(data=st.data())
def test_truncations_and_bit_flips_are_refused(data):
    msg = data.draw(st.sampled_from(sample_messages()))
    key = data.draw(st.sampled_from([None, KEY]))
    wire = encode(msg, key)
    cut = data.draw(st.integers(0, len(wire) - 1))
    with pytest.raises(ProtocolError):
        decode(wire[:cut], key)
    bit = data.draw(st.integers(0, 8 * len(wire) - 1))
    flipped = bytearray(wire)
    flipped[bit // 8] ^= 1 << (bit % 8)
    # A CRC-32 catches every single-bit error, an HMAC every change at all.
    with pytest.raises(ProtocolError):
        decode(bytes(flipped), key)


@settings(max_examples=200)
@given(data=st.data())
def test_mutated_bodies_behind_a_valid_trailer_raise_protocol_error_only(data):
    """Bytes that pass the CRC but hold a damaged body: only ProtocolError or a valid message."""
    msg = data.draw(st.sampled_from(sample_messages()))
    wire = encode(msg)
    body = bytearray(wire[4:-4])
    for _ in range(data.draw(st.integers(1, 4))):
        body[data.draw(st.integers(0, len(body) - 1))] = data.draw(st.integers(0, 255))
    with contextlib.suppress(ProtocolError):
        decode(raw_bytes(bytes(body)))


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(width=64)
    | st.text(max_size=70)
    | st.binary(max_size=40),
    lambda inner: (
        st.lists(inner, max_size=8)
        | st.dictionaries(st.text(max_size=3) | st.binary(max_size=3), inner, max_size=4)
    ),
    max_leaves=12,
)


def _paths(obj, path=()):
    yield path
    if isinstance(obj, (dict, list)):
        items = obj.items() if isinstance(obj, dict) else enumerate(obj)
    else:
        items = ()
    for k, v in items:
        yield from _paths(v, (*path, k))


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_structurally_mutated_bodies_raise_protocol_error_only(data):
    """Any field of any kind replaced by any msgpack value: ProtocolError or a valid message."""
    wire = encode(data.draw(st.sampled_from(sample_messages())))
    body = msgpack.unpackb(wire[4:-4], raw=False)
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from(list(_paths(body))[1:]))
        parent = body
        for k in path[:-1]:
            parent = parent[k]
        parent[path[-1]] = data.draw(msgpack_values)
    with contextlib.suppress(ProtocolError):
        decode(raw(body))


def raw_bytes(body: bytes) -> bytes:
    head = MAGIC + bytes((SCHEMA_VERSION, 0))
    return head + body + seal(head + body, None)


def test_wrong_schema_version():
    with pytest.raises(ProtocolError, match="unsupported schema version 2"):
        decode(raw({"k": "heartbeat", "f": "f", "r": "r", "n": 1, "mv": None}, schema=2))


def test_truncated_message():
    wire = encode(sample_messages()[0])
    with pytest.raises(ProtocolError, match=r"CRC mismatch|truncated"):
        decode(wire[:-1])
    with pytest.raises(ProtocolError, match="truncated"):
        decode(wire[:3])


def test_corrupted_message():
    wire = bytearray(encode(sample_messages()[1]))
    wire[10] ^= 0xFF
    with pytest.raises(ProtocolError, match="corrupted message: CRC mismatch"):
        decode(bytes(wire))


def test_tile_checksum_mismatch():
    cells = np.ones((16, 16), np.int8)
    with pytest.raises(ProtocolError, match="tile 0: checksum mismatch"):
        decode(raw(tile_body(cells, crc=checksum(cells) ^ 1)))


def test_nan_is_refused_everywhere_a_float_travels():
    link = {
        "k": "link", "f": "f", "d": "a", "a": "a", "b": "b", "va": 1, "vb": 2, "ok": True,
        "m": [1.0, 0, 0, 0, 1, 0, 0, 0, 1], "cov": [1.0, 0, 0, 0, 1, 0, 0, 0, 1], "s": 0.5,
    }  # fmt: skip
    for field, value in [("s", math.nan), ("m", [math.nan, *link["m"][1:]])]:
        with pytest.raises(ProtocolError, match="finite"):
            decode(raw({**link, field: value}))
    with pytest.raises(ProtocolError, match="finite"):
        decode(raw({"k": "status", "f": "f", "r": "r", "n": 1, "c": {"x": math.inf}}))
    body = tile_body(np.ones((16, 16), np.int8))
    body["g"][2] = math.nan
    with pytest.raises(ProtocolError, match="resolution must be finite"):
        decode(raw(body))


def test_tile_shape_mismatch():
    # Tile 0 of a 20x30 map with 16-cell tiles is 16x16; 15x16 cells inflate short.
    with pytest.raises(ProtocolError, match="inflates to 240 bytes, expected 256"):
        decode(raw(tile_body(np.ones((15, 16), np.int8))))
    with pytest.raises(ProtocolError, match="tile index 6 outside"):
        body = tile_body(np.ones((16, 16), np.int8))
        body["t"][0][0] = 6
        decode(raw(body))
    g = [20, 30, 0.05, 0.0, 0.0, 0.0, 16]  # 2x2 tiles
    manifest = {"k": "manifest", "f": "f", "r": "r", "v": 1, "g": g, "b": None, "d": None}
    beyond = np.packbits([0, 0, 0, 0, 1, 0, 0, 0]).tobytes() + bytes(4)
    with pytest.raises(ProtocolError, match="bits beyond the last tile"):
        decode(raw({**manifest, "c": beyond}))
    short = np.packbits([1, 1, 0, 0, 0, 0, 0, 0]).tobytes() + bytes(4)
    with pytest.raises(ProtocolError, match="lists 2 tiles but carries 4 checksum bytes"):
        decode(raw({**manifest, "c": short}))


def test_too_many_cells():
    body = tile_body(np.ones((16, 16), np.int8), shape=(5000, 5000), ts=256)
    with pytest.raises(ProtocolError, match="25000000 cells exceeds the limit"):
        decode(raw(body))


def test_too_many_tiles():
    limits = Limits(max_tiles=3)
    with pytest.raises(ProtocolError, match="4 tiles exceeds the limit 3"):
        decode(raw(tile_body(np.ones((16, 16), np.int8))), limits=limits)
    msg = MapTiles(
        "f", "r", 1, Geometry((64, 64), 0.05, tile_size=16),
        tuple(Tile(i, 0, np.zeros((16, 16), np.int8)) for i in range(3)),
    )  # fmt: skip
    with pytest.raises(ProtocolError, match="3 tiles in one message exceed the limit of 2"):
        decode(encode(msg), limits=Limits(max_tiles_per_message=2))


def test_too_many_bytes():
    wire = encode(sample_messages()[0])
    with pytest.raises(ProtocolError, match=f"message of {len(wire)} bytes exceeds the limit"):
        decode(wire, limits=Limits(max_message_bytes=len(wire) - 1))


def test_decompression_bomb_is_bounded():
    """A ~10 KB message whose tile inflates to 10 MB: refused, with a small allocation."""
    bomb = zlib.compressobj(9, zlib.DEFLATED, -15)
    packed = bomb.compress(bytes(10_000_000)) + bomb.flush()
    body = tile_body(np.zeros((16, 16), np.int8), shape=(256, 256), ts=256)
    body["t"][0][4] = packed
    wire = raw(body)
    assert len(wire) < 12_000
    tracemalloc.start()
    try:
        with pytest.raises(ProtocolError, match="expands past its bound of 65536 bytes"):
            decode(wire)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000


def test_unknown_kind_and_fields():
    with pytest.raises(ProtocolError, match="unknown message kind 'gossip'"):
        decode(raw({"k": "gossip"}))
    body = {"k": "heartbeat", "f": "f", "r": "r", "n": 1, "mv": None, "extra": 1, b"x": 2}
    with pytest.raises(ProtocolError, match="unknown fields 'extra', b'x'"):
        decode(raw(body))
    with pytest.raises(ProtocolError, match="lacks field 'n'"):
        decode(raw({"k": "heartbeat", "f": "f", "r": "r", "mv": None}))
    with pytest.raises(ProtocolError, match="wrong type bool"):
        decode(raw({"k": "heartbeat", "f": "f", "r": "r", "n": True, "mv": None}))


def test_bad_ids():
    for robot, why in [("a/b", "characters outside"), ("x" * 65, "1..64"), ("", "1..64")]:
        with pytest.raises(ProtocolError, match=why):
            decode(raw({"k": "heartbeat", "f": "f", "r": robot, "n": 1, "mv": None}))
    with pytest.raises(ProtocolError, match="longer than 8"):
        decode(
            raw({"k": "heartbeat", "f": "f", "r": "r" * 9, "n": 1, "mv": None}),
            limits=Limits(max_id_length=8),
        )


def test_out_of_range_cell_value():
    cells = np.full((16, 16), -128, np.int8)
    with pytest.raises(ProtocolError, match="-128 is outside the quantised range"):
        decode(raw(tile_body(cells)))


@pytest.mark.parametrize("key", [None, KEY])
def test_batched_tile_encoding_matches_encode_of_the_same_message(key):
    msg = sample_messages()[0]
    assert encode_tiles(msg, key, 60_000) == [encode(msg, key)]
    with pytest.raises(ProtocolError, match="does not fit in 100-byte messages"):
        encode_tiles(msg, key, 100)


def test_cells_decoded_from_one_message_are_bounded():
    """240 empty 256x256 tiles deflate to ~30 KB but would inflate to 15 MB: refused."""
    g = Geometry((3840, 4096), 0.05, tile_size=256)
    zeros = np.zeros((256, 256), np.int8)
    msg = MapTiles("f", "r", 1, g, tuple(Tile(i, checksum(zeros), zeros) for i in range(240)))
    wire = encode(msg)
    assert len(wire) < 40_000
    tracemalloc.start()
    try:
        with pytest.raises(ProtocolError, match="exceed the limit of 1048576 cells"):
            decode(wire)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4_000_000
    # encode_map's batching keeps every message within that limit.
    parts = encode_tiles(msg, None, 60_000)
    assert len(parts) == 15 and all(len(decode(p).tiles) == 16 for p in parts)
