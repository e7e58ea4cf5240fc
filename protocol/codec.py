"""Messages to bytes and back: msgpack, a versioned header, a CRC or MAC trailer.

Wire layout of every message::

    b"PG" | schema version (1 byte) | flags (1 byte) | msgpack body | trailer

``flags`` bit 0 says the trailer is an HMAC-SHA256 (32 bytes, fleet key set)
rather than a CRC-32 (4 bytes).  The body is a msgpack map whose ``"k"``
entry names the kind; every other entry is checked for type, range and
finiteness before a message object is built.  Tiles are deflate streams
(:mod:`protocol.compress`) inflated with a hard bound derived from the tile's
own shape, so a small message can never expand into a large allocation.
A manifest's checksums travel as a bitmap of the tiles it lists followed by
one little-endian CRC-32 per listed tile (:func:`protocol.tiles.pack_checksums`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np

from protocol.auth import check_key, seal, unseal
from protocol.compress import pack_cells, unpack_cells
from protocol.errors import ProtocolError
from protocol.limits import Limits
from protocol.messages import (
    Geometry,
    Heartbeat,
    Link,
    Manifest,
    MapTiles,
    Message,
    Status,
    Tile,
    check_id,
)
from protocol.tiles import apply_tile, pack_checksums

MAGIC = b"PG"
#: Bumped on any incompatible change of the body layout.
SCHEMA_VERSION = 1
FLAG_MAC = 0x01
HEADER_BYTES = 4

KIND_TILES = "tiles"
KIND_MANIFEST = "manifest"
KIND_LINK = "link"
KIND_HEARTBEAT = "heartbeat"
KIND_STATUS = "status"


# ---------------------------------------------------------------- encoding


def encode(msg: Message, key: bytes | None = None) -> bytes:
    """Serialise ``msg``; with a fleet ``key`` it carries an HMAC-SHA256, else a CRC-32.

    Raises
    ------
    ProtocolError
        If ``msg`` is not a message of this protocol or the key is not bytes.
    """
    key = check_key(key)
    body = msgpack.packb(_body(msg), use_bin_type=True)
    head = MAGIC + bytes((SCHEMA_VERSION, FLAG_MAC if key is not None else 0))
    return head + body + seal(head + body, key)


def _geometry(g: Geometry) -> list[Any]:
    return [g.shape[0], g.shape[1], g.resolution, *g.origin, g.tile_size]


def _tile(t: Tile) -> list[Any]:
    encoding, packed = pack_cells(t.cells)
    return [t.index, t.checksum, t.base_checksum, encoding, packed]


def _tiles_body(msg: MapTiles, tiles: list[Any]) -> dict[str, Any]:
    """The body of a MapTiles message around already packed ``tiles``; "t" comes last."""
    return {
        "k": KIND_TILES,
        "f": msg.fleet,
        "r": msg.robot,
        "v": msg.version,
        "g": _geometry(msg.geometry),
        "b": msg.base_version,
        "t": tiles,
    }


def _body(msg: Message) -> dict[str, Any]:
    if isinstance(msg, MapTiles):
        return _tiles_body(msg, [_tile(t) for t in msg.tiles])
    if isinstance(msg, Manifest):
        return {
            "k": KIND_MANIFEST,
            "f": msg.fleet,
            "r": msg.robot,
            "v": msg.version,
            "g": _geometry(msg.geometry),
            "c": pack_checksums(msg.geometry, msg.checksums),
            "b": msg.base_version,
            "d": msg.digest,
        }
    if isinstance(msg, Link):
        return {
            "k": KIND_LINK,
            "f": msg.fleet,
            "d": msg.decided_by,
            "a": msg.robot_a,
            "b": msg.robot_b,
            "va": msg.version_a,
            "vb": msg.version_b,
            "ok": msg.accepted,
            "m": [v for row in msg.matrix for v in row],
            "cov": [v for row in msg.covariance for v in row],
            "s": msg.score,
        }
    if isinstance(msg, Heartbeat):
        return {
            "k": KIND_HEARTBEAT,
            "f": msg.fleet,
            "r": msg.robot,
            "n": msg.seq,
            "mv": msg.map_version,
        }
    if isinstance(msg, Status):
        return {
            "k": KIND_STATUS,
            "f": msg.fleet,
            "r": msg.robot,
            "n": msg.seq,
            "c": dict(msg.counters),
        }
    raise ProtocolError(f"cannot encode a {type(msg).__name__}")


# ---------------------------------------------------------------- decoding


def decode(data: bytes, key: bytes | None = None, limits: Limits = Limits()) -> Message:  # noqa: B008
    """Parse and validate one message; the only exception raised is ProtocolError.

    The trailer (CRC-32, or HMAC-SHA256 with a fleet ``key``) is checked before
    the body is parsed, so unauthenticated bytes never reach msgpack.

    Raises
    ------
    ProtocolError
        On any malformed, oversized, corrupted, unauthenticated or invalid input.
    """
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"message must be bytes, got {type(data).__name__}")
    data = bytes(data)
    key = check_key(key)
    if len(data) > limits.max_message_bytes:
        raise ProtocolError(
            f"message of {len(data)} bytes exceeds the limit of {limits.max_message_bytes}"
        )
    if len(data) < HEADER_BYTES:
        raise ProtocolError(f"truncated message: {len(data)} bytes, header needs {HEADER_BYTES}")
    if data[:2] != MAGIC:
        raise ProtocolError("not a pgvd message: bad magic")
    if data[2] != SCHEMA_VERSION:
        raise ProtocolError(f"unsupported schema version {data[2]} (this decoder speaks 1)")
    flags = data[3]
    if flags & ~FLAG_MAC:
        raise ProtocolError(f"unknown flags 0x{flags:02x}")
    covered = unseal(data, bool(flags & FLAG_MAC), key)
    try:
        body = msgpack.unpackb(
            covered[HEADER_BYTES:], raw=False, strict_map_key=True, use_list=True
        )
    except Exception as exc:  # msgpack raises a zoo of types on bad input
        raise ProtocolError(f"malformed msgpack body: {type(exc).__name__}") from None
    if not isinstance(body, dict):
        raise ProtocolError("message body must be a map")
    kind = body.get("k")
    parser = _PARSERS.get(kind) if isinstance(kind, str) else None
    if parser is None:
        raise ProtocolError(f"unknown message kind {kind!r}")
    return parser(_Fields(body, kind), limits)


class _Fields:
    """The entries of one body map, taken one by one; leftovers are an error."""

    def __init__(self, body: dict[str, Any], kind: str) -> None:
        self._body = dict(body)
        self._body.pop("k")
        self.kind = kind

    def take(self, name: str, types: type | tuple[type, ...], nullable: bool = False) -> Any:
        if name not in self._body:
            raise ProtocolError(f"{self.kind} message lacks field {name!r}")
        value = self._body.pop(name)
        if value is None and nullable:
            return None
        allowed = types if isinstance(types, tuple) else (types,)
        if isinstance(value, bool) and bool not in allowed:
            raise ProtocolError(f"{self.kind} field {name!r} has the wrong type bool")
        if not isinstance(value, types):
            raise ProtocolError(
                f"{self.kind} field {name!r} has the wrong type {type(value).__name__}"
            )
        return value

    def done(self) -> None:
        if self._body:
            names = ", ".join(sorted(map(repr, self._body)))  # keys may be str or bytes
            raise ProtocolError(f"{self.kind} message has unknown fields {names}")


def _id(fields: _Fields, name: str, what: str, limits: Limits) -> str:
    value = check_id(fields.take(name, str), what)
    if len(value) > limits.max_id_length:
        raise ProtocolError(f"{what} longer than {limits.max_id_length} characters")
    return value


def _parse_geometry(fields: _Fields, limits: Limits) -> Geometry:
    g = fields.take("g", list)
    if len(g) != 7:
        raise ProtocolError(f"geometry must have 7 entries, got {len(g)}")
    geometry = Geometry((g[0], g[1]), g[2], (g[3], g[4], g[5]), g[6])
    h, w = geometry.shape
    if h > limits.max_side or w > limits.max_side:
        raise ProtocolError(f"map of {h}x{w} cells exceeds the side limit {limits.max_side}")
    if h * w > limits.max_cells:
        raise ProtocolError(f"map of {h * w} cells exceeds the limit of {limits.max_cells}")
    if geometry.n_tiles > limits.max_tiles:
        raise ProtocolError(f"map of {geometry.n_tiles} tiles exceeds the limit {limits.max_tiles}")
    if geometry.tile_size**2 > limits.max_tile_cells:
        raise ProtocolError(f"tile of {geometry.tile_size**2} cells exceeds the limit")
    return geometry


def _parse_tile(raw: Any, geometry: Geometry) -> Tile:
    if not isinstance(raw, list) or len(raw) != 5:
        raise ProtocolError("a tile must be [index, checksum, base_checksum, encoding, data]")
    index, crc, base, encoding, packed = raw
    if isinstance(index, bool) or not isinstance(index, int):
        raise ProtocolError("tile index must be an integer")
    shape = geometry.tile_shape(index)
    if isinstance(encoding, bool) or not isinstance(encoding, int):
        raise ProtocolError(f"tile {index}: encoding must be an integer")
    if not isinstance(packed, bytes):
        raise ProtocolError(f"tile {index}: data must be bytes")
    tile = Tile(index, crc, unpack_cells(encoding, packed, shape, index), base)
    if not tile.is_delta:
        apply_tile(tile, None)  # a delta's checksum can only be checked against its base
    return tile


def _parse_tiles(fields: _Fields, limits: Limits) -> MapTiles:
    fleet = _id(fields, "f", "fleet", limits)
    robot = _id(fields, "r", "robot", limits)
    version = fields.take("v", int)
    geometry = _parse_geometry(fields, limits)
    base_version = fields.take("b", int, nullable=True)
    raw_tiles = fields.take("t", list)
    fields.done()
    if len(raw_tiles) > limits.max_tiles_per_message:
        raise ProtocolError(
            f"{len(raw_tiles)} tiles in one message exceed the limit of "
            f"{limits.max_tiles_per_message}"
        )
    tiles, cells = [], 0
    for raw in raw_tiles:
        tile = _parse_tile(raw, geometry)
        cells += tile.cells.size
        # Checked after each bounded inflate: never more than one tile past the limit.
        if cells > limits.max_message_cells:
            raise ProtocolError(
                f"tiles of one message exceed the limit of {limits.max_message_cells} cells"
            )
        tiles.append(tile)
    return MapTiles(fleet, robot, version, geometry, tuple(tiles), base_version)


def _parse_manifest(fields: _Fields, limits: Limits) -> Manifest:
    fleet = _id(fields, "f", "fleet", limits)
    robot = _id(fields, "r", "robot", limits)
    version = fields.take("v", int)
    geometry = _parse_geometry(fields, limits)
    packed = fields.take("c", bytes)
    base_version = fields.take("b", int, nullable=True)
    digest = fields.take("d", int, nullable=True)
    fields.done()
    n = geometry.n_tiles
    bitmap = -(-n // 8)
    if len(packed) < bitmap:
        raise ProtocolError(f"manifest checksums of {len(packed)} bytes miss the {n}-tile bitmap")
    bits = np.unpackbits(np.frombuffer(packed, np.uint8, bitmap))
    if bits[n:].any():
        raise ProtocolError("manifest bitmap has bits beyond the last tile")
    listed = np.flatnonzero(bits[:n])
    if len(packed) != bitmap + 4 * len(listed):
        raise ProtocolError(
            f"manifest lists {len(listed)} tiles but carries {len(packed) - bitmap} checksum bytes"
        )
    crcs = np.frombuffer(packed, "<u4", offset=bitmap)
    checksums = {int(i): int(c) for i, c in zip(listed, crcs, strict=True)}
    return Manifest(fleet, robot, version, geometry, checksums, base_version, digest)


def _matrix(fields: _Fields, name: str) -> list[list[Any]]:
    flat = fields.take(name, list)
    if len(flat) != 9:
        raise ProtocolError(f"{name} must hold 9 numbers, got {len(flat)}")
    return [flat[0:3], flat[3:6], flat[6:9]]


def _parse_link(fields: _Fields, limits: Limits) -> Link:
    fleet = _id(fields, "f", "fleet", limits)
    decided_by = _id(fields, "d", "decided_by", limits)
    robot_a = _id(fields, "a", "robot_a", limits)
    robot_b = _id(fields, "b", "robot_b", limits)
    version_a = fields.take("va", int)
    version_b = fields.take("vb", int)
    accepted = fields.take("ok", bool)
    matrix = _matrix(fields, "m")
    covariance = _matrix(fields, "cov")
    score = fields.take("s", (int, float))
    fields.done()
    return Link(
        fleet, decided_by, robot_a, robot_b, version_a, version_b, accepted, matrix, covariance,
        score,
    )  # fmt: skip


def _parse_heartbeat(fields: _Fields, limits: Limits) -> Heartbeat:
    fleet = _id(fields, "f", "fleet", limits)
    robot = _id(fields, "r", "robot", limits)
    seq = fields.take("n", int)
    map_version = fields.take("mv", int, nullable=True)
    fields.done()
    return Heartbeat(fleet, robot, seq, map_version)


def _parse_status(fields: _Fields, limits: Limits) -> Status:
    fleet = _id(fields, "f", "fleet", limits)
    robot = _id(fields, "r", "robot", limits)
    seq = fields.take("n", int)
    counters = fields.take("c", dict)
    fields.done()
    if len(counters) > limits.max_status_entries:
        raise ProtocolError(
            f"{len(counters)} counters exceed the limit of {limits.max_status_entries}"
        )
    return Status(fleet, robot, seq, counters)


_PARSERS: dict[str, Callable[[_Fields, Limits], Message]] = {
    KIND_TILES: _parse_tiles,
    KIND_MANIFEST: _parse_manifest,
    KIND_LINK: _parse_link,
    KIND_HEARTBEAT: _parse_heartbeat,
    KIND_STATUS: _parse_status,
}


def encode_tiles(msg: MapTiles, key: bytes | None, max_message_bytes: int) -> list[bytes]:
    """Encode the tiles of ``msg`` as several MapTiles messages, each under ``max_message_bytes``.

    Every tile is compressed once; tiles are packed greedily in index order.

    Raises
    ------
    ProtocolError
        If one tile alone does not fit in ``max_message_bytes``.
    """
    key = check_key(key)
    head = MAGIC + bytes((SCHEMA_VERSION, FLAG_MAC if key is not None else 0))
    trailer = len(seal(b"", key))
    # Packed once with an empty tile list, whose 1-byte array header ends the body.
    prefix = msgpack.packb(_tiles_body(msg, []), use_bin_type=True)[:-1]
    # Stay within what a decoder with default limits accepts.
    limits = Limits()
    # The array header takes at most 3 bytes for up to 2**16 tiles.
    fixed = len(head) + len(prefix) + 3 + trailer
    batches: list[list[bytes]] = [[]]
    size, cells = fixed, 0
    for tile in msg.tiles:
        entry = msgpack.packb(_tile(tile), use_bin_type=True)
        if fixed + len(entry) >= max_message_bytes:
            raise ProtocolError(
                f"a tile of {len(entry)} bytes does not fit in {max_message_bytes}-byte messages"
            )
        if (
            size + len(entry) >= max_message_bytes
            or cells + tile.cells.size > limits.max_message_cells
            or len(batches[-1]) >= limits.max_tiles_per_message
        ):
            batches.append([])
            size, cells = fixed, 0
        batches[-1].append(entry)
        size += len(entry)
        cells += tile.cells.size
    out = []
    for batch in batches:
        body = prefix + _array_header(len(batch)) + b"".join(batch)
        out.append(head + body + seal(head + body, key))
    return out


def _array_header(n: int) -> bytes:
    """msgpack array header for ``n < 2**16`` elements."""
    return bytes((0x90 | n,)) if n < 16 else b"\xdc" + n.to_bytes(2, "big")
