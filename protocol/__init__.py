"""The wire format, sans-I/O: typed messages to bytes and back, strictly validated.

Nothing here opens a socket, touches Zenoh or reads a clock; every rule is a
pure function of bytes and state you pass in (h11 / hyper-h2 style).

Messages (:mod:`protocol.messages`, frozen dataclasses)
    ``Geometry(shape, resolution, origin, tile_size=128)``,
    ``Tile(index, checksum, cells: int8 ndarray, base_checksum=None)``,
    ``MapTiles(fleet, robot, version, geometry, tiles, base_version=None)``,
    ``Manifest(fleet, robot, version, geometry, checksums: {tile index: crc32},
    base_version=None, digest=None, first_epoch=None, final=False)`` (a delta manifest when
    base_version is set; ``first_epoch``, the epoch of the robot's first version, and
    ``final``, the mark of the robot's last version, trailing fields a manifest may leave
    out: an older manifest reads as not saying and not final),
    ``Link(fleet, decided_by, robot_a, robot_b, version_a, version_b, accepted,
    matrix 3x3, covariance 3x3, score, trust=None)``, ``trust`` a
    ``LinkTrust(state, margin, first_margin, reason, first_version_a, first_version_b, holds,
    revision)``
    (None: a link of the older format, which the decoder still reads),
    ``Heartbeat(fleet, robot, seq, map_version=None)``,
    ``Status(fleet, robot, seq, counters: {str: int | float})``.

Bytes (:mod:`protocol.codec`)
    ``encode(msg, key=None) -> bytes`` and
    ``decode(data, key=None, limits=Limits()) -> Message``; ``decode`` raises
    :class:`ProtocolError` and nothing else; its ``reason`` is one of
    ``REASONS`` (framing, auth, schema, limit, value, replay) for counting drops.
    With a fleet ``key`` every message carries an HMAC-SHA256 and unkeyed or wrongly keyed ones are
    refused; without one, a CRC-32 catches corruption.

Maps (:mod:`protocol.mapsync`)
    ``encode_map(fleet, robot, version, grid, key=None, since=None,
    base_version=None, max_message_bytes=60_000, tile_size=128, indices=None,
    lone_oversize=False, first_epoch=None, final=False) -> (tile_messages: list[bytes],
    manifest: bytes)``:
    log-odds quantised to int8 (:mod:`protocol.quantize`), cut into 128x128
    tiles, only tiles holding knowledge sent, each in the smallest of three
    byte layouts, the layouts of one message compressed as one stream by
    deflate, LZMA or, for the few sparse cells of a small delta, an adaptive arithmetic coder
    (:mod:`protocol.compress`, :mod:`protocol.arith`); with ``since`` (the Grid or int8 array of an
    earlier version) only changed tiles, as differences, and with
    ``base_version`` too a delta manifest (only changed tiles' checksums plus a
    digest of the full list: bytes proportional to the change; a receiver
    lacking ``base_version`` reports every tile missing and should fetch the
    full latest version, tiles and full manifest); with ``indices``
    exactly those tiles in full (a queryable's answer to ``missing()``; indices
    without knowledge are skipped).  Each tile message is under
    ``max_message_bytes`` (pass e.g. 20_000 for about one tile per message);
    ``tile_messages`` is empty when nothing changed since ``since``.

    ``MapReassembler(robot, fleet=None, limits=Limits())``, one per peer robot:
    ``feed(msg) -> Grid | None`` returns the complete grid when every tile of
    the newest manifest is held (older versions are ignored; tiles ahead of
    their manifest are buffered, bounded by ``limits.max_buffered_cells``);
    ``missing() -> list[int]`` names the tile indices to fetch, e.g. a delta
    whose base this receiver never had; ``version``, ``quantised``,
    ``first_epoch`` and ``final`` hold the last complete one; ``dropped`` counts buffered
    messages that contradicted their manifest.  A sender's versions must keep
    growing across its restarts.

Fetches (:mod:`protocol.fetch`)
    ``fetch_parameters(version, indices) -> dict | None`` names the tiles a receiver lacks as
    a query's selector parameters (None: ask for the whole map), and
    ``parse_fetch(v, tiles) -> TileFetch | None`` reads them back on the queryable's side,
    bounded, raising ProtocolError like every decoder.

Replays (:mod:`protocol.auth`)
    ``ReplayGuard(state=None).admit(msg)`` raises ProtocolError unless the
    message's version moves forward for its (robot, kind): per sequence number
    for Heartbeat/Status, per map version for Manifest, per tile index (full
    and delta apart) for MapTiles, per (version_a, version_b) for Link.  Call it
    after ``decode``; persist ``guard.state`` to refuse replays across restarts.
    Only meaningful with a fleet key: without one anybody can forge new versions.

Wire layout (:mod:`protocol.codec`, schema version 3)
    ``b"PG" | schema version | flags | msgpack body | CRC-32 or HMAC-SHA256``;
    the body is a positional msgpack array (kind first); the trailer is
    checked before the body is parsed, decompressing is bounded by the tile
    shapes of the message's tile table, and every field is type-, range- and
    finiteness-checked.  A full tile's checksum is computed by the receiver.
"""

from protocol.auth import ReplayGuard
from protocol.codec import SCHEMA_VERSION, decode, encode, peek_map
from protocol.errors import REASONS, ProtocolError
from protocol.fetch import MAX_FETCH_TILES, TileFetch, fetch_parameters, parse_fetch
from protocol.limits import Limits
from protocol.mapsync import MapReassembler, encode_map, quantise_grid
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
)
from protocol.quantize import SCALE, dequantise, quantise

__all__ = [
    "MAX_FETCH_TILES",
    "REASONS",
    "SCALE",
    "SCHEMA_VERSION",
    "Geometry",
    "Heartbeat",
    "Limits",
    "Link",
    "LinkTrust",
    "Manifest",
    "MapReassembler",
    "MapTiles",
    "Message",
    "ProtocolError",
    "ReplayGuard",
    "Status",
    "Tile",
    "TileFetch",
    "decode",
    "dequantise",
    "encode",
    "encode_map",
    "fetch_parameters",
    "parse_fetch",
    "peek_map",
    "quantise",
    "quantise_grid",
]
