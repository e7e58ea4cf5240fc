"""protocol.codec: round trips, and every way a message can be refused."""

from __future__ import annotations

import contextlib
import lzma
import math
import zlib

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from refusals import refused, refused_within

from pgvd.io import read_map
from protocol import (
    REASONS,
    Geometry,
    Heartbeat,
    Limits,
    Link,
    LinkTrust,
    Manifest,
    MapTiles,
    ProtocolError,
    Status,
    Tile,
    decode,
    encode,
    quantise_grid,
)
from protocol.auth import seal
from protocol.codec import (
    KIND_HEARTBEAT,
    KIND_LINK,
    KIND_MANIFEST,
    KIND_STATUS,
    KIND_TILES,
    MAGIC,
    SCHEMA_VERSION,
    encode_tiles,
)
from protocol.compress import ARITH, DEFLATE, LZMA, RAW, SPARSE
from protocol.tiles import checksum

KEY = b"fleet-key-for-tests-0123456789ab"

ids = st.from_regex(r"[A-Za-z0-9][A-Za-z0-9_-]{0,20}", fullmatch=True)
versions = st.integers(0, 2**63 - 1)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
matrices = st.lists(finite, min_size=9, max_size=9).map(lambda v: np.array(v).reshape(3, 3))


def raw(body: list, key: bytes | None = None, schema: int = SCHEMA_VERSION) -> bytes:
    """A sealed message around a hand-made body, to reach the checks behind the trailer."""
    head = MAGIC + bytes((schema, 1 if key else 0))
    payload = head + msgpack.packb(body, use_bin_type=True)
    return payload + seal(payload, key)


def entry(index: int, encoding: int, size: int, delta: tuple[int, int] | None = None) -> bytes:
    """One tile-table entry (index, flags, layout size and a delta's two CRC-32s)."""
    out = bytes((index, encoding | (0x80 if delta else 0), *_leb128(size)))
    if delta:
        out += delta[0].to_bytes(4, "little") + delta[1].to_bytes(4, "little")
    return out


def _leb128(n: int) -> bytes:
    out = bytearray()
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    return bytes((*out, n))


def tile_body(cells: np.ndarray, shape=(20, 30), ts=16, table: bytes | None = None) -> list:
    """A tiles body holding tile 0 (``cells`` as a RAW layout, deflated) of a map of ``shape``."""
    packer = zlib.compressobj(6, zlib.DEFLATED, -15)
    stream = packer.compress(cells.tobytes()) + packer.flush()
    table = entry(0, RAW, cells.size) if table is None else table
    geometry = [shape[0], shape[1], 0.05, 0.0, 0.0, 0.0, ts]
    return [KIND_TILES, "fleet", "r1", 3, geometry, None, table, DEFLATE, stream]


def heartbeat(*fields) -> list:
    return [KIND_HEARTBEAT, *(fields or ("f", "r", 1, None))]


def sample_messages() -> list:
    g = Geometry((20, 30), 0.05, (1.0, -2.0, 0.1), 16)
    cells = np.arange(16 * 16, dtype=np.int64).reshape(16, 16).astype(np.int8) % 100
    cells = cells.astype(np.int8)
    # A scan-like delta: a few cells along a ray, on two tiles (the arithmetic coder's case).
    ray = np.zeros((16, 16), np.int8)
    ray[np.arange(2, 12), np.arange(3, 13)] = -3
    ray[12, 13] = 6
    edge = np.zeros((16, 14), np.int8)
    edge[4:7, 2] = [-2, -3, -3]
    delta = (Tile(0, 5, ray, base_checksum=6), Tile(1, 7, edge, base_checksum=8))
    return [
        MapTiles("fleet", "r1", 3, g, (Tile(0, checksum(cells), cells),)),
        MapTiles("fleet", "r1", 4, g, delta, base_version=3),
        Manifest("fleet", "r1", 3, g, {0: checksum(cells), 3: 7}),
        Manifest("fleet", "r1", 4, g, {1: 9}, base_version=3, digest=2**64 - 1),
        Manifest("fleet", "r1", 5, g, {1: 9}, base_version=4, digest=7, first_epoch=2**32 - 1),
        Manifest("fleet", "r1", 6, g, {1: 9}, first_epoch=5, final=True),
        Link("fleet", "r1", "r1", "r2", 3, 4, True, np.eye(3), np.eye(3) * 0.5, 0.93),
        Link(
            "fleet",
            "r1",
            "r1",
            "r2",
            3,
            4,
            False,
            np.eye(3),
            np.eye(3) * 0.5,
            0.61,
            LinkTrust("candidate", 0.41, 0.3, "grey zone: margin 0.41 below 0.57", 2, 4, 1, 1),
        ),
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
            for a, b in zip(out.tiles, msg.tiles, strict=True):
                assert (a.index, a.checksum, a.base_checksum) == (
                    b.index,
                    b.checksum,
                    b.base_checksum,
                )
                assert np.array_equal(a.cells, b.cells)
        else:
            assert out == msg


def test_the_sample_delta_is_arithmetic_coded():
    """So that the fuzz tests below also reach the arithmetic decoder through whole messages."""
    assert msgpack.unpackb(encode(sample_messages()[1])[4:-4])[7] == ARITH


def test_bytes_like_input_and_non_bytes():
    wire = encode(Heartbeat("f", "r", 1))
    assert decode(bytearray(wire)) == decode(memoryview(wire)) == Heartbeat("f", "r", 1)
    with refused("framing", "message must be bytes, got str"):
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


states = st.sampled_from(("accepted", "candidate", "confirmed", "rejected", "withdrawn"))
# printable: no control characters, and no separator but the space
reasons = st.text(
    st.characters(blacklist_categories=("C", "Z"), max_codepoint=0x2FF) | st.just(" "),
    max_size=400,
)


@given(
    va=versions, vb=versions, state=states, margin=st.none() | finite,
    first=st.none() | finite, reason=reasons,
    back=st.tuples(st.integers(0, 2**40), st.integers(0, 2**40)),
    counts=st.tuples(st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1)),
)  # fmt: skip
def test_link_with_its_lifecycle_round_trips(va, vb, state, margin, first, reason, back, counts):
    firsts = (max(va - back[0], 0), max(vb - back[1], 0))
    trust = LinkTrust(state, margin, first, reason, *firsts, *counts)
    accepted = state in ("accepted", "confirmed")
    msg = Link("f", "r1", "r1", "r2", va, vb, accepted, np.eye(3), np.eye(3), 0.5, trust)
    assert decode(encode(msg, KEY), KEY) == msg


def test_a_link_of_the_older_format_is_read_without_a_lifecycle():
    old = [KIND_LINK, "f", "r1", "r1", "r2", 3, 4, False, [1, 0, 0, 0, 1, 0, 0, 0, 1],
           [0] * 9, 0.5]  # fmt: skip
    msg = decode(raw(old))
    assert isinstance(msg, Link) and msg.trust is None and not msg.accepted


@pytest.mark.parametrize(
    ("trust", "reason", "why"),
    [
        (["maybe", 0.4, None, "", 3, 4, 0, 0], "value", "link state must be one of"),
        (["candidate", 0.4, None, "", 3, 4, 0], "schema", "lacks field 'revision'"),
        (["candidate", 0.4, None, "", 3, 4, 0, 0, 9], "schema", "1 unknown trailing fields"),
        (["candidate", float("nan"), None, "", 3, 4, 0, 0], "value", "margin must be finite"),
        (["candidate", 0.4, float("inf"), "", 3, 4, 0, 0], "value", "first_margin must be"),
        (["candidate", 0.4, None, "x" * 401, 3, 4, 0, 0], "limit", "reason of 401 characters"),
        (["candidate", 0.4, None, "a\nb", 3, 4, 0, 0], "value", "unprintable"),
        (["candidate", 0.4, None, "", 5, 4, 0, 0], "value", "first versions are newer"),
        (["candidate", 0.4, None, "", 3, 4, -1, 0], "value", "holds must be in"),
        (["candidate", 0.4, None, "", 3, 4, 0, 2**32], "value", "revision must be <="),
        (["accepted", 0.4, None, "", 3, 4, 0, 0], "value", "accepted link cannot have"),
        ("candidate", "schema", "field 'trust' has the wrong type str"),
    ],
)
def test_a_links_lifecycle_is_checked_strictly(trust, reason, why):
    body = [KIND_LINK, "f", "r1", "r1", "r2", 3, 4, False, [1, 0, 0, 0, 1, 0, 0, 0, 1],
            [0] * 9, 0.5, trust]  # fmt: skip
    with refused(reason, why):
        decode(raw(body))


@given(
    robot=ids, version=versions, first=st.none() | st.integers(0, 2**32 - 1),
    delta=st.booleans(), final=st.booleans(),
    tiles=st.dictionaries(st.integers(0, 3), st.integers(0, 2**32 - 1), max_size=4),
)  # fmt: skip
def test_manifest_with_a_first_epoch_and_a_final_mark_round_trips(
    robot, version, first, delta, final, tiles
):
    g = Geometry((20, 30), 0.05, (1.0, -2.0, 0.1), 16)
    since = {"base_version": version - 1, "digest": 3} if delta and version else {}
    msg = Manifest("f", robot, version, g, tiles, **since, first_epoch=first, final=final)
    got = decode(encode(msg, KEY), KEY)
    assert got == msg and got.final is final


def manifest_body(*trailing) -> list:
    bitmap = bytes(1)  # 4 tiles of 20x30 at 16, none listed
    return [KIND_MANIFEST, "f", "r1", 3, [20, 30, 0.05, 0, 0, 0, 16], bitmap, None, None,
            *trailing]  # fmt: skip


def test_a_manifest_without_a_first_epoch_is_read_as_not_saying():
    msg = decode(raw(manifest_body()))
    assert isinstance(msg, Manifest) and msg.first_epoch is None
    assert decode(raw(manifest_body(9))).first_epoch == 9


def test_a_manifest_without_the_final_mark_is_read_as_not_final():
    """Manifests of earlier agents end before the mark (or before the first epoch)."""
    assert [decode(raw(manifest_body(*t))).final for t in ((), (9,))] == [False, False]
    marked = decode(raw(manifest_body(9, True)))
    assert (marked.first_epoch, marked.final) == (9, True)
    unknown_age = decode(raw(manifest_body(None, True)))
    assert (unknown_age.first_epoch, unknown_age.final) == (None, True)
    # a manifest that is not final says nothing more than an older one: the same bytes
    g = Geometry((20, 30), 0.05, (0.0, 0.0, 0.0), 16)
    plain = encode(Manifest("f", "r1", 3, g, {}, first_epoch=9))
    assert msgpack.unpackb(plain[4:-4])[8:] == [9]  # after the digest: the first epoch alone


@pytest.mark.parametrize(
    ("trailing", "reason", "why"),
    [
        ((2**32,), "value", "first_epoch must be a 32-bit unsigned integer"),
        ((-1,), "value", "first_epoch must be a 32-bit unsigned integer"),
        ((1.5,), "schema", "field 'first_epoch' has the wrong type float"),
        ((None,), "schema", "field 'first_epoch' has the wrong type NoneType"),
        ((True,), "schema", "field 'first_epoch' has the wrong type bool"),
        ((1, 2), "schema", "field 'final' has the wrong type int"),
        ((1, None), "schema", "field 'final' has the wrong type NoneType"),
        ((1, False), "value", "final mark, when present, must be true"),
        ((None, False), "value", "final mark, when present, must be true"),
        ((1, True, 2), "schema", "manifest message has 1 unknown trailing fields"),
    ],
)
def test_a_manifests_first_epoch_and_final_mark_are_checked_strictly(trailing, reason, why):
    with refused(reason, why):
        decode(raw(manifest_body(*trailing)))


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
        with pytest.raises(ProtocolError) as err:
            decode(data, key)
        assert err.value.reason in REASONS


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


@settings(max_examples=200)
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
    with refused("schema", r"unsupported schema version 2 \(this decoder speaks 3\)"):
        decode(raw(heartbeat(), schema=2))


def test_truncated_message():
    wire = encode(sample_messages()[0])
    with refused("framing", r"CRC mismatch|truncated"):
        decode(wire[:-1])
    with refused("framing", "truncated"):
        decode(wire[:3])


def test_corrupted_message():
    wire = bytearray(encode(sample_messages()[1]))
    wire[10] ^= 0xFF
    with refused("framing", "corrupted message: CRC mismatch"):
        decode(bytes(wire))


def test_full_tiles_carry_the_checksum_of_their_cells():
    """The wire has no checksum for a full tile: the receiver computes it, the sender checks it."""
    cells = np.ones((16, 16), np.int8)
    g = Geometry((20, 30), 0.05, tile_size=16)
    assert decode(raw(tile_body(cells))).tiles[0].checksum == checksum(cells)
    wrong = MapTiles("f", "r", 1, g, (Tile(0, checksum(cells) ^ 1, cells),))
    with refused("value", "tile 0: checksum mismatch"):
        encode(wrong)


def test_delta_tiles_carry_both_checksums():
    diff = np.zeros((16, 16), np.int8)
    diff[3, 4] = -3
    g = Geometry((20, 30), 0.05, tile_size=16)
    msg = MapTiles("f", "r", 2, g, (Tile(0, 11, diff, base_checksum=22),), base_version=1)
    tile = decode(encode(msg)).tiles[0]
    assert (tile.checksum, tile.base_checksum, tile.cells.tolist()) == (11, 22, diff.tolist())


def test_nan_is_refused_everywhere_a_float_travels():
    eye = [1.0, 0, 0, 0, 1, 0, 0, 0, 1]
    link = [KIND_LINK, "f", "a", "a", "b", 1, 2, True, eye, eye, 0.5]
    for at, value in [(10, math.nan), (8, [math.nan, *eye[1:]])]:
        with refused("value", "finite"):
            decode(raw([*link[:at], value, *link[at + 1 :]]))
    with refused("value", "finite"):
        decode(raw([KIND_STATUS, "f", "r", 1, {"x": math.inf}]))
    body = tile_body(np.ones((16, 16), np.int8))
    body[4][2] = math.nan
    with refused("value", "resolution must be finite"):
        decode(raw(body))


def test_tile_shape_mismatch():
    # Tile 0 of a 20x30 map with 16-cell tiles is 16x16; 15x16 cells make a short layout.
    with refused("value", r"raw tile of 240 bytes, shape \(16, 16\)"):
        decode(raw(tile_body(np.ones((15, 16), np.int8), table=entry(0, RAW, 240))))
    with refused("value", "tile index 6 outside"):
        decode(raw(tile_body(np.ones((16, 16), np.int8), table=entry(6, RAW, 256))))
    with refused("value", "stream decompresses to 200 bytes, the tiles need 256"):
        decode(raw(tile_body(np.ones((10, 20), np.int8), table=entry(0, RAW, 256))))
    with refused("limit", "stream expands past its bound of 200 bytes"):
        decode(raw(tile_body(np.ones((16, 16), np.int8), table=entry(0, RAW, 200))))
    with refused("limit", "layout of 257 bytes exceeds its bound"):
        decode(raw(tile_body(np.ones((16, 16), np.int8), table=entry(0, RAW, 257))))
    with refused("framing", "tile table is truncated"):
        decode(raw(tile_body(np.ones((16, 16), np.int8), table=entry(0, RAW, 256)[:-1])))
    with refused("schema", "unknown encoding 5"):
        decode(raw(tile_body(np.ones((16, 16), np.int8), table=entry(0, 5, 256))))
    g = [20, 30, 0.05, 0.0, 0.0, 0.0, 16]  # 2x2 tiles
    beyond = np.packbits([0, 0, 0, 0, 1, 0, 0, 0]).tobytes() + bytes(4)
    with refused("schema", "bits beyond the last tile"):
        decode(raw([KIND_MANIFEST, "f", "r", 1, g, beyond, None, None]))
    short = np.packbits([1, 1, 0, 0, 0, 0, 0, 0]).tobytes() + bytes(4)
    with refused("schema", "lists 2 tiles but carries 4 checksum bytes"):
        decode(raw([KIND_MANIFEST, "f", "r", 1, g, short, None, None]))


def test_too_many_cells():
    body = tile_body(np.ones((16, 16), np.int8), shape=(5000, 5000), ts=256)
    with refused("limit", "25000000 cells exceeds the limit"):
        decode(raw(body))


def test_too_many_tiles():
    limits = Limits(max_tiles=3)
    with refused("limit", "4 tiles exceeds the limit 3"):
        decode(raw(tile_body(np.ones((16, 16), np.int8))), limits=limits)
    msg = MapTiles(
        "f", "r", 1, Geometry((64, 64), 0.05, tile_size=16),
        tuple(Tile(i, checksum(np.zeros((16, 16), np.int8)), np.zeros((16, 16), np.int8))
              for i in range(3)),
    )  # fmt: skip
    with refused("limit", "more than 2 tiles in one message exceed the limit"):
        decode(encode(msg), limits=Limits(max_tiles_per_message=2))


def test_too_many_bytes():
    wire = encode(sample_messages()[0])
    with refused("limit", f"message of {len(wire)} bytes exceeds the limit"):
        decode(wire, limits=Limits(max_message_bytes=len(wire) - 1))


def _bomb(codec: int) -> bytes:
    """~10 KB that would decompress to 10 MB."""
    if codec == LZMA:
        filters = [{"id": lzma.FILTER_LZMA2, "dict_size": 1 << 18}]
        return lzma.compress(bytes(10_000_000), format=lzma.FORMAT_RAW, filters=filters)
    bomb = zlib.compressobj(9, zlib.DEFLATED, -15)
    return bomb.compress(bytes(10_000_000)) + bomb.flush()


@pytest.mark.parametrize("codec", [DEFLATE, LZMA])
def test_decompression_bomb_is_bounded(codec):
    """A ~10 KB message whose stream decompresses to 10 MB: refused, with a small allocation."""
    body = tile_body(np.zeros((16, 16), np.int8), shape=(256, 256), ts=256)
    body[6] = entry(0, RAW, 65536)
    body[7:] = [codec, _bomb(codec)]
    wire = raw(body)
    assert len(wire) < 12_000
    with refused_within("limit", "expands past its bound of 65536 bytes", 1_000_000):
        decode(wire)


def test_codecs_are_chosen_by_size(shared):
    """Building-map cells go to LZMA, a few sparse cells to the arithmetic coder, and
    streams too long for LZMA's time budget (here noise) to deflate."""
    rng = np.random.default_rng(3)
    g = Geometry((640, 640), 0.05, tile_size=128)
    willow = read_map(shared / "maps" / "willow" / "willow-2010-02-18-0.10.yaml")
    building = [np.ascontiguousarray(quantise_grid(willow)[256:384, 128:256])]
    sparse = [np.zeros((128, 128), np.int8)]
    sparse[0][rng.integers(0, 128, 40), rng.integers(0, 128, 40)] = -3
    noise = list(rng.integers(-127, 128, (20, 128, 128)).astype(np.int8))
    for tiles, codec in [(building, LZMA), (sparse, ARITH), (noise, DEFLATE)]:
        msg = MapTiles("f", "r", 1, g, tuple(Tile(i, checksum(c), c) for i, c in enumerate(tiles)))
        wire = encode(msg)
        assert msgpack.unpackb(wire[4:-4])[7] == codec
        out = decode(wire, limits=Limits(max_message_bytes=10**6)).tiles
        assert all(np.array_equal(a.cells, b) for a, b in zip(out, tiles, strict=True))


def test_arithmetic_coded_stream_of_non_sparse_tiles_is_refused():
    body = tile_body(np.ones((16, 16), np.int8))
    body[7] = ARITH
    with refused("schema", "sparse tiles only"):
        decode(raw(body))
    body[6] = entry(0, SPARSE, 3)
    with refused("framing", "arithmetic-coded stream"):
        decode(raw(body))


def test_unknown_kind_and_fields():
    with refused("schema", "unknown message kind 9"):
        decode(raw([9, "f"]))
    with refused("schema", "unknown message kind 'gossip'"):
        decode(raw(["gossip"]))
    with refused("schema", "body must be a non-empty array"):
        decode(raw({"k": "heartbeat"}))
    with refused("schema", "heartbeat message has 2 unknown trailing fields"):
        decode(raw(heartbeat("f", "r", 1, None, 1, b"x")))
    with refused("schema", "lacks field 'map_version'"):
        decode(raw(heartbeat("f", "r", 1)))
    with refused("schema", "wrong type bool"):
        decode(raw(heartbeat("f", "r", True, None)))


def test_bad_ids():
    for robot, reason, why in [
        ("a/b", "value", "characters outside"),
        ("x" * 65, "limit", "1..64"),
        ("", "value", "1..64"),
    ]:
        with refused(reason, why):
            decode(raw(heartbeat("f", robot, 1, None)))
    with refused("limit", "longer than 8"):
        decode(raw(heartbeat("f", "r" * 9, 1, None)), limits=Limits(max_id_length=8))


def test_out_of_range_cell_value():
    cells = np.full((16, 16), -128, np.int8)
    with refused("value", "-128 is outside the quantised range"):
        decode(raw(tile_body(cells)))


@pytest.mark.parametrize("key", [None, KEY])
def test_batched_tile_encoding_matches_encode_of_the_same_message(key):
    msg = sample_messages()[0]
    assert encode_tiles(msg, key, 60_000) == [encode(msg, key)]
    with refused("limit", "does not fit in 100-byte messages"):
        encode_tiles(msg, key, 100)


def test_cells_decoded_from_one_message_are_bounded():
    """240 empty 256x256 tiles deflate to ~30 KB but would inflate to 15 MB: refused."""
    g = Geometry((3840, 4096), 0.05, tile_size=256)
    zeros = np.zeros((256, 256), np.int8)
    msg = MapTiles("f", "r", 1, g, tuple(Tile(i, checksum(zeros), zeros) for i in range(240)))
    wire = encode(msg)
    assert len(wire) < 40_000
    with refused_within("limit", "exceed the limit of 1048576 cells", 4_000_000):
        decode(wire)
    # encode_map's batching keeps every message within that limit.
    parts = encode_tiles(msg, None, 60_000)
    assert len(parts) == 15 and all(len(decode(p).tiles) == 16 for p in parts)


def test_a_reason_outside_the_fixed_set_is_a_programming_error():
    assert ProtocolError("x", reason="auth").reason == "auth"
    with pytest.raises(ValueError, match="unknown ProtocolError reason 'bad'"):
        ProtocolError("x", reason="bad")


DIGEST_GEOMETRY = Geometry((20, 20), 0.05, tile_size=16)


@given(digest=st.integers(0, 2**64 - 1), base=st.integers(0, 2**63 - 2))
def test_any_64_bit_digest_round_trips(digest, base):
    m = Manifest("f", "r", base + 1, DIGEST_GEOMETRY, {0: 1}, base_version=base, digest=digest)
    assert decode(encode(m)) == m


@given(digest=st.integers(-(2**63), -1))
def test_a_negative_digest_on_the_wire_is_refused(digest):
    """msgpack carries signed ints too: the decoder must refuse them, not build a Manifest."""
    body = [KIND_MANIFEST, "f", "r", 2, [20, 20, 0.05, 0, 0, 0, 16], b"\x00", 1, digest]
    with refused("value", "64-bit unsigned"):
        decode(raw(body))
