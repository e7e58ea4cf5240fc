"""Messages to bytes and back: msgpack, a versioned header, a CRC or MAC trailer.

Wire layout of every message::

    b"PG" | schema version (1 byte) | flags (1 byte) | msgpack body | trailer

``flags`` bit 0 says the trailer is an HMAC-SHA256 (32 bytes, fleet key set)
rather than a CRC-32 (4 bytes).  The body is a msgpack array whose first
entry is the kind (a small integer) and whose other entries are the kind's
fields in a fixed order (no field names on the wire: a one-scan delta is a
few hundred bytes, where names would be a tenth of it); every field is checked
for type, range and finiteness before a message object is built.

A MapTiles body ends in a tile table and ONE compressed stream holding the
layouts of all its tiles (:mod:`protocol.compress`).  Per tile the table
holds the index and layout (LEB128 varints), a flags byte (layout id, bit 7
set for a delta tile) and, for delta tiles only, the little-endian CRC-32s of
the result and of its base: a full tile's checksum is computed from its cells
by the receiver, since the trailer already covers the bytes.  The table bounds
every layout by its tile's shape before anything is decompressed, so a small
message can never expand into a large allocation.  A manifest's checksums
travel as a bitmap of the tiles it lists followed by one little-endian CRC-32
per listed tile (:func:`protocol.tiles.pack_checksums`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import msgpack
import numpy as np

from protocol.auth import check_key, seal, unseal
from protocol.compress import compress, decompress, layout_bound, layout_cells, unpack_layout
from protocol.errors import ProtocolError
from protocol.limits import Limits
from protocol.messages import (
    Geometry,
    Heartbeat,
    Link,
    LinkTrust,
    Manifest,
    MapTiles,
    Message,
    Status,
    Tile,
    check_id,
)
from protocol.tiles import checksum, pack_checksums

MAGIC = b"PG"
#: Bumped on any incompatible change of the body layout (2: positional bodies, one
#: compressed stream per tile message; 3: a manifest's trailing ``first_epoch``, which the
#: merged frame's anchor is chosen by, so a fleet must not mix agents that lack it).
SCHEMA_VERSION = 3
FLAG_MAC = 0x01
HEADER_BYTES = 4
DELTA_BIT = 0x80

KIND_TILES = 0
KIND_MANIFEST = 1
KIND_LINK = 2
KIND_HEARTBEAT = 3
KIND_STATUS = 4


# ---------------------------------------------------------------- encoding


def encode(msg: Message, key: bytes | None = None) -> bytes:
    """Serialise ``msg``; with a fleet ``key`` it carries an HMAC-SHA256, else a CRC-32.

    Raises
    ------
    ProtocolError
        If ``msg`` is not a message of this protocol or the key is not bytes.
    """
    key = check_key(key)
    if isinstance(msg, MapTiles):
        return _seal_tiles(msg, [_layout(t) for t in msg.tiles], key)
    return _seal(_body(msg), key)


def _seal(body: list[Any], key: bytes | None) -> bytes:
    head = MAGIC + bytes((SCHEMA_VERSION, FLAG_MAC if key is not None else 0))
    packed = head + msgpack.packb(body, use_bin_type=True)
    return packed + seal(packed, key)


def _geometry(g: Geometry) -> list[Any]:
    return [g.shape[0], g.shape[1], *map(_compact, (g.resolution, *g.origin)), g.tile_size]


def _compact(x: float) -> float | int:
    """``x`` as an int when it is one (a yaw of 0.0 packs in 1 byte, not 9), else as is.

    Lossless: the decoder takes ints wherever floats travel (only the sign of
    -0.0 is dropped, and -0.0 == 0.0).
    """
    return int(x) if x.is_integer() and abs(x) < 2**53 else x


class _Layout:
    """One tile laid out for the wire: its layout id, table entry, layout bytes and shape."""

    __slots__ = ("encoding", "entry", "layout", "shape")

    def __init__(self, encoding: int, entry: bytes, layout: bytes, shape: tuple[int, int]) -> None:
        self.encoding, self.entry, self.layout, self.shape = encoding, entry, layout, shape


def _layout(t: Tile) -> _Layout:
    if not t.is_delta and checksum(t.cells) != t.checksum:
        # The wire carries no checksum for a full tile: the receiver computes it.
        raise ProtocolError(f"tile {t.index}: checksum mismatch", reason="value")
    encoding, layout = layout_cells(t.cells)
    entry = _varint(t.index) + bytes((encoding | (DELTA_BIT if t.is_delta else 0),))
    entry += _varint(len(layout))
    if t.is_delta:
        entry += t.checksum.to_bytes(4, "little") + t.base_checksum.to_bytes(4, "little")
    return _Layout(encoding, entry, layout, t.cells.shape)


def _varint(n: int) -> bytes:
    """LEB128: 7 bits per byte, low bits first, high bit set on all but the last byte."""
    out = bytearray()
    while n >= 0x80:
        out.append((n & 0x7F) | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def _seal_tiles(msg: MapTiles, layouts: Sequence[_Layout], key: bytes | None) -> bytes:
    """One MapTiles message holding ``layouts`` (tiles of ``msg``) in one compressed stream."""
    codec, stream = compress([(t.encoding, t.layout, t.shape) for t in layouts])
    return _seal(_tiles_body(msg, b"".join(t.entry for t in layouts), codec, stream), key)


def _tiles_body(msg: MapTiles, table: bytes, codec: int, stream: bytes) -> list[Any]:
    return [
        KIND_TILES, msg.fleet, msg.robot, msg.version, _geometry(msg.geometry),
        msg.base_version, table, codec, stream,
    ]  # fmt: skip


def _body(msg: Message) -> list[Any]:
    if isinstance(msg, Manifest):
        return [
            KIND_MANIFEST, msg.fleet, msg.robot, msg.version, _geometry(msg.geometry),
            pack_checksums(msg.geometry, msg.checksums), msg.base_version, msg.digest,
            *_manifest_tail(msg),
        ]  # fmt: skip
    if isinstance(msg, Link):
        return [
            KIND_LINK, msg.fleet, msg.decided_by, msg.robot_a, msg.robot_b, msg.version_a,
            msg.version_b, msg.accepted, [_compact(v) for row in msg.matrix for v in row],
            [_compact(v) for row in msg.covariance for v in row], _compact(msg.score),
            *([] if msg.trust is None else [_trust(msg.trust)]),
        ]  # fmt: skip
    if isinstance(msg, Heartbeat):
        return [KIND_HEARTBEAT, msg.fleet, msg.robot, msg.seq, msg.map_version]
    if isinstance(msg, Status):
        return [KIND_STATUS, msg.fleet, msg.robot, msg.seq, dict(msg.counters)]
    raise ProtocolError(f"cannot encode a {type(msg).__name__}", reason="schema")


def _manifest_tail(msg: Manifest) -> list[Any]:
    """A manifest's trailing fields, each left out when it says nothing: the first epoch,
    then the final mark (present only when true, after a nil first epoch if that is
    unknown).  Manifests of earlier agents end before either."""
    if msg.final:
        return [msg.first_epoch, True]
    return [] if msg.first_epoch is None else [msg.first_epoch]


def _trust(trust: LinkTrust) -> list[Any]:
    """A link's lifecycle as the one trailing field of its body (older links have none)."""
    margins = [None if m is None else _compact(m) for m in (trust.margin, trust.first_margin)]
    return [
        trust.state, *margins, trust.reason, trust.first_version_a, trust.first_version_b,
        trust.holds, trust.revision,
    ]  # fmt: skip


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
    covered = _open(data, key, limits)
    try:
        body = msgpack.unpackb(
            covered[HEADER_BYTES:], raw=False, strict_map_key=True, use_list=True
        )
    except Exception as exc:  # msgpack raises a zoo of types on bad input
        raise ProtocolError(
            f"malformed msgpack body: {type(exc).__name__}", reason="schema"
        ) from None
    if not isinstance(body, list) or not body:
        raise ProtocolError("message body must be a non-empty array", reason="schema")
    kind = body[0]
    entry = None if isinstance(kind, bool) or not isinstance(kind, int) else _PARSERS.get(kind)
    if entry is None:
        raise ProtocolError(f"unknown message kind {kind!r}", reason="schema")
    name, parser = entry
    return parser(_Fields(body[1:], name), limits)


def peek_map(
    data: bytes,
    key: bytes | None = None,
    limits: Limits = Limits(),  # noqa: B008
) -> tuple[bool, str, int] | None:
    """``(is_tiles, robot, version)`` of a map message, or None for any other payload.

    Authenticated like :func:`decode`, but only the first fields of the body are read and
    nothing is decompressed: a receiver can tell which queued tiles a newer version
    supersedes at the cost of the trailer's check. None says nothing about validity:
    :func:`decode` still decides.
    """
    try:
        covered = _open(data, key, limits)
        unpacker = msgpack.Unpacker(raw=False, strict_map_key=True)
        unpacker.feed(covered[HEADER_BYTES:])
        if unpacker.read_array_header() < 4:
            return None
        kind, _, robot, version = (unpacker.unpack() for _ in range(4))
    except Exception:  # whatever is wrong, decode() will say what
        return None
    if not all(type(v) is t for v, t in ((kind, int), (robot, str), (version, int))):
        return None  # bool is an int subclass: an exact type check refuses it
    return (kind == KIND_TILES, robot, version) if kind in (KIND_TILES, KIND_MANIFEST) else None


def _open(data: bytes, key: bytes | None, limits: Limits) -> bytes:
    """The bytes a message's trailer covers, header included, once framing and trailer hold."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"message must be bytes, got {type(data).__name__}", reason="framing")
    data = bytes(data)
    key = check_key(key)
    if len(data) > limits.max_message_bytes:
        raise ProtocolError(
            f"message of {len(data)} bytes exceeds the limit of {limits.max_message_bytes}",
            reason="limit",
        )
    if len(data) < HEADER_BYTES:
        raise ProtocolError(
            f"truncated message: {len(data)} bytes, header needs {HEADER_BYTES}", reason="framing"
        )
    if data[:2] != MAGIC:
        raise ProtocolError("not a pgvd message: bad magic", reason="framing")
    if data[2] != SCHEMA_VERSION:
        raise ProtocolError(
            f"unsupported schema version {data[2]} (this decoder speaks {SCHEMA_VERSION})",
            reason="schema",
        )
    flags = data[3]
    if flags & ~FLAG_MAC:
        raise ProtocolError(f"unknown flags 0x{flags:02x}", reason="schema")
    return unseal(data, bool(flags & FLAG_MAC), key)


class _Fields:
    """The fields of one positional body, taken in order by name; leftovers are an error."""

    def __init__(self, values: list[Any], kind: str) -> None:
        self._values = values
        self._next = 0
        self.kind = kind

    def take(self, name: str, types: type | tuple[type, ...], nullable: bool = False) -> Any:
        if self._next >= len(self._values):
            raise ProtocolError(f"{self.kind} message lacks field {name!r}", reason="schema")
        value = self._values[self._next]
        self._next += 1
        if value is None and nullable:
            return None
        allowed = types if isinstance(types, tuple) else (types,)
        if isinstance(value, bool) and bool not in allowed:
            raise ProtocolError(
                f"{self.kind} field {name!r} has the wrong type bool", reason="schema"
            )
        if not isinstance(value, types):
            raise ProtocolError(
                f"{self.kind} field {name!r} has the wrong type {type(value).__name__}",
                reason="schema",
            )
        return value

    def more(self) -> bool:
        """Whether fields remain: a body that grew a trailing field reads both forms."""
        return self._next < len(self._values)

    def left(self) -> int:
        """How many fields remain."""
        return len(self._values) - self._next

    def done(self) -> None:
        extra = len(self._values) - self._next
        if extra:
            raise ProtocolError(
                f"{self.kind} message has {extra} unknown trailing fields", reason="schema"
            )


def _id(fields: _Fields, name: str, what: str, limits: Limits) -> str:
    value = check_id(fields.take(name, str), what)
    if len(value) > limits.max_id_length:
        raise ProtocolError(f"{what} longer than {limits.max_id_length} characters", reason="limit")
    return value


def _parse_geometry(fields: _Fields, limits: Limits) -> Geometry:
    g = fields.take("geometry", list)
    if len(g) != 7:
        raise ProtocolError(f"geometry must have 7 entries, got {len(g)}", reason="schema")
    geometry = Geometry((g[0], g[1]), g[2], (g[3], g[4], g[5]), g[6])
    h, w = geometry.shape
    if h > limits.max_side or w > limits.max_side:
        raise ProtocolError(
            f"map of {h}x{w} cells exceeds the side limit {limits.max_side}", reason="limit"
        )
    if h * w > limits.max_cells:
        raise ProtocolError(
            f"map of {h * w} cells exceeds the limit of {limits.max_cells}", reason="limit"
        )
    if geometry.n_tiles > limits.max_tiles:
        raise ProtocolError(
            f"map of {geometry.n_tiles} tiles exceeds the limit {limits.max_tiles}", reason="limit"
        )
    if geometry.tile_size**2 > limits.max_tile_cells:
        raise ProtocolError(
            f"tile of {geometry.tile_size**2} cells exceeds the limit", reason="limit"
        )
    return geometry


class _Reader:
    """A cursor over a tile table; running out of bytes is a ProtocolError."""

    def __init__(self, data: bytes) -> None:
        self.data, self.pos = data, 0

    def __bool__(self) -> bool:
        return self.pos < len(self.data)

    def byte(self) -> int:
        if self.pos >= len(self.data):
            raise ProtocolError("tile table is truncated", reason="framing")
        self.pos += 1
        return self.data[self.pos - 1]

    def varint(self) -> int:
        value = 0
        for shift in range(0, 64, 7):
            b = self.byte()
            value |= (b & 0x7F) << shift
            if not b & 0x80:
                return value
        raise ProtocolError("tile table holds a varint longer than 64 bits", reason="framing")

    def crc(self) -> int:
        if self.pos + 4 > len(self.data):
            raise ProtocolError("tile table is truncated", reason="framing")
        self.pos += 4
        return int.from_bytes(self.data[self.pos - 4 : self.pos], "little")


def _parse_table(
    table: bytes, geometry: Geometry, limits: Limits
) -> list[tuple[int, int, int, int | None, int | None]]:
    """``(index, encoding, layout bytes, checksum, base checksum)`` per tile, bounded."""
    entries, cells = [], 0
    reader = _Reader(table)
    while reader:
        if len(entries) >= limits.max_tiles_per_message:
            raise ProtocolError(
                f"more than {limits.max_tiles_per_message} tiles in one message exceed the limit",
                reason="limit",
            )
        index = reader.varint()
        shape = geometry.tile_shape(index)
        flags = reader.byte()
        encoding = flags & ~DELTA_BIT
        size = reader.varint()
        if size > layout_bound(encoding, shape, index):
            raise ProtocolError(
                f"tile {index}: layout of {size} bytes exceeds its bound", reason="limit"
            )
        crc, base = (reader.crc(), reader.crc()) if flags & DELTA_BIT else (None, None)
        cells += shape[0] * shape[1]
        if cells > limits.max_message_cells:
            raise ProtocolError(
                f"tiles of one message exceed the limit of {limits.max_message_cells} cells",
                reason="limit",
            )
        entries.append((index, encoding, size, crc, base))
    if not entries:
        raise ProtocolError("a tiles message must carry at least one tile", reason="schema")
    return entries


def _tile(index: int, cells: np.ndarray, crc: int | None, base: int | None) -> Tile:
    if crc is None:
        if cells.min(initial=0) == -128:
            raise ProtocolError(
                f"tile {index}: cell value -128 is outside the quantised range", reason="value"
            )
        return Tile(index, checksum(cells), cells)
    # A delta's checksum can only be checked against its base, when it is applied.
    return Tile(index, crc, cells, base)


def _parse_tiles(fields: _Fields, limits: Limits) -> MapTiles:
    fleet = _id(fields, "fleet", "fleet", limits)
    robot = _id(fields, "robot", "robot", limits)
    version = fields.take("version", int)
    geometry = _parse_geometry(fields, limits)
    base_version = fields.take("base_version", int, nullable=True)
    entries = _parse_table(fields.take("table", bytes), geometry, limits)
    codec = fields.take("codec", int)
    stream = fields.take("stream", bytes)
    fields.done()
    data = decompress(codec, stream, [(e[1], e[2], geometry.tile_shape(e[0])) for e in entries])
    tiles, at = [], 0
    for index, encoding, size, crc, base in entries:
        cells = unpack_layout(encoding, data[at : at + size], geometry.tile_shape(index), index)
        at += size
        tiles.append(_tile(index, cells, crc, base))
    return MapTiles(fleet, robot, version, geometry, tuple(tiles), base_version)


def _parse_manifest(fields: _Fields, limits: Limits) -> Manifest:
    fleet = _id(fields, "fleet", "fleet", limits)
    robot = _id(fields, "robot", "robot", limits)
    version = fields.take("version", int)
    geometry = _parse_geometry(fields, limits)
    packed = fields.take("checksums", bytes)
    base_version = fields.take("base_version", int, nullable=True)
    digest = fields.take("digest", int, nullable=True)
    # A manifest that does not say its robot's first epoch ends here; one of its robot's
    # last version carries the final mark after it (the first epoch nil when unknown).
    marked = fields.left() > 1
    first_epoch = fields.take("first_epoch", int, nullable=marked) if fields.more() else None
    final = fields.take("final", bool) if marked else False
    if marked and not final:
        raise ProtocolError("a manifest's final mark, when present, must be true", reason="value")
    fields.done()
    n = geometry.n_tiles
    bitmap = -(-n // 8)
    if len(packed) < bitmap:
        raise ProtocolError(
            f"manifest checksums of {len(packed)} bytes miss the {n}-tile bitmap", reason="schema"
        )
    bits = np.unpackbits(np.frombuffer(packed, np.uint8, bitmap))
    if bits[n:].any():
        raise ProtocolError("manifest bitmap has bits beyond the last tile", reason="schema")
    listed = np.flatnonzero(bits[:n])
    if len(packed) != bitmap + 4 * len(listed):
        raise ProtocolError(
            f"manifest lists {len(listed)} tiles but carries {len(packed) - bitmap} checksum bytes",
            reason="schema",
        )
    crcs = np.frombuffer(packed, "<u4", offset=bitmap)
    checksums = dict(zip(listed.tolist(), crcs.tolist(), strict=True))
    return Manifest(
        fleet, robot, version, geometry, checksums, base_version, digest, first_epoch, final
    )


def _matrix(fields: _Fields, name: str) -> list[list[Any]]:
    flat = fields.take(name, list)
    if len(flat) != 9:
        raise ProtocolError(f"{name} must hold 9 numbers, got {len(flat)}", reason="schema")
    return [flat[0:3], flat[3:6], flat[6:9]]


def _parse_link(fields: _Fields, limits: Limits) -> Link:
    fleet = _id(fields, "fleet", "fleet", limits)
    decided_by = _id(fields, "decided_by", "decided_by", limits)
    robot_a = _id(fields, "robot_a", "robot_a", limits)
    robot_b = _id(fields, "robot_b", "robot_b", limits)
    version_a = fields.take("version_a", int)
    version_b = fields.take("version_b", int)
    accepted = fields.take("accepted", bool)
    matrix = _matrix(fields, "matrix")
    covariance = _matrix(fields, "covariance")
    score = fields.take("score", (int, float))
    # A link of the older format ends here; the current one carries its lifecycle.
    trust = _parse_trust(fields.take("trust", list)) if fields.more() else None
    fields.done()
    return Link(
        fleet, decided_by, robot_a, robot_b, version_a, version_b, accepted, matrix, covariance,
        score, trust,
    )  # fmt: skip


def _parse_trust(values: list[Any]) -> LinkTrust:
    trust = _Fields(values, "link trust")
    out = LinkTrust(
        trust.take("state", str),
        trust.take("margin", (int, float), nullable=True),
        trust.take("first_margin", (int, float), nullable=True),
        trust.take("reason", str),
        trust.take("first_version_a", int),
        trust.take("first_version_b", int),
        trust.take("holds", int),
        trust.take("revision", int),
    )
    trust.done()
    return out


def _parse_heartbeat(fields: _Fields, limits: Limits) -> Heartbeat:
    fleet = _id(fields, "fleet", "fleet", limits)
    robot = _id(fields, "robot", "robot", limits)
    seq = fields.take("seq", int)
    map_version = fields.take("map_version", int, nullable=True)
    fields.done()
    return Heartbeat(fleet, robot, seq, map_version)


def _parse_status(fields: _Fields, limits: Limits) -> Status:
    fleet = _id(fields, "fleet", "fleet", limits)
    robot = _id(fields, "robot", "robot", limits)
    seq = fields.take("seq", int)
    counters = fields.take("counters", dict)
    fields.done()
    if len(counters) > limits.max_status_entries:
        raise ProtocolError(
            f"{len(counters)} counters exceed the limit of {limits.max_status_entries}",
            reason="limit",
        )
    return Status(fleet, robot, seq, counters)


_PARSERS: dict[int, tuple[str, Callable[[_Fields, Limits], Message]]] = {
    KIND_TILES: ("tiles", _parse_tiles),
    KIND_MANIFEST: ("manifest", _parse_manifest),
    KIND_LINK: ("link", _parse_link),
    KIND_HEARTBEAT: ("heartbeat", _parse_heartbeat),
    KIND_STATUS: ("status", _parse_status),
}


def encode_tiles(
    msg: MapTiles, key: bytes | None, max_message_bytes: int, lone_oversize: bool = False
) -> list[bytes]:
    """Encode the tiles of ``msg`` as several MapTiles messages, each under ``max_message_bytes``.

    Every tile is laid out once; tiles are batched in their order up to the
    cells and tiles a decoder with default :class:`Limits` accepts in one
    message, and a batch whose message comes out too large is split in two.
    With ``lone_oversize`` a tile that alone exceeds ``max_message_bytes``
    travels in a message of its own instead: a best-effort sender packs tiles
    into datagrams, and only such a tile then rides IP fragmentation.

    Raises
    ------
    ProtocolError
        If one tile alone does not fit in ``max_message_bytes`` (without
        ``lone_oversize``), or not in a message a default decoder accepts.
    """
    key = check_key(key)
    limits = Limits()
    batches: list[list[_Layout]] = [[]]
    cells = 0
    for tile in msg.tiles:
        if batches[-1] and (
            cells + tile.cells.size > limits.max_message_cells
            or len(batches[-1]) >= limits.max_tiles_per_message
        ):
            batches.append([])
            cells = 0
        batches[-1].append(_layout(tile))
        cells += tile.cells.size
    lone_limit = limits.max_message_bytes if lone_oversize else max_message_bytes
    return [
        wire for batch in batches for wire in _fit(msg, batch, key, max_message_bytes, lone_limit)
    ]


def _fit(
    msg: MapTiles, batch: list[_Layout], key: bytes | None, limit: int, lone_limit: int
) -> list[bytes]:
    """``batch`` as one message, or split in halves until every message is under ``limit``.

    A message of a single tile may reach ``lone_limit`` (>= ``limit``).
    """
    wire = _seal_tiles(msg, batch, key)
    if len(wire) < limit or (len(batch) == 1 and len(wire) < lone_limit):
        return [wire]
    if len(batch) == 1:
        raise ProtocolError(
            f"a tile of {len(wire)} bytes does not fit in {limit}-byte messages", reason="limit"
        )
    half = len(batch) // 2
    return _fit(msg, batch[:half], key, limit, lone_limit) + _fit(
        msg, batch[half:], key, limit, lone_limit
    )
