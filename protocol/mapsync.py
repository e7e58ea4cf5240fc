"""Publishing a map as tile messages plus a manifest, and rebuilding it on the other side.

The agent publishes each tile message on its own Zenoh key (for example
``pgvd/<fleet>/tiles/<robot>/<version>/<first tile>``) and the manifest on
``pgvd/<fleet>/manifest/<robot>``; a receiver feeds whatever arrives, in any
order, to a :class:`MapReassembler` and asks a queryable for the tile indices
:meth:`MapReassembler.missing` names.  Nothing here touches the network.
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np

from pgvd.grid import Grid
from protocol.codec import encode, encode_tiles
from protocol.errors import ProtocolError
from protocol.limits import Limits
from protocol.messages import DEFAULT_TILE_SIZE, Geometry, Manifest, MapTiles, Message, check_id
from protocol.quantize import dequantise, quantise
from protocol.tiles import (
    TileAssembler,
    changed_tiles,
    check_quantised,
    delta_tile,
    expand_manifest,
    full_tile,
    manifest_checksums,
    manifest_digest,
    zero_checksum,
)


def quantise_grid(grid: Grid) -> np.ndarray:
    """The int8 cells of ``grid`` exactly as they travel (see :mod:`protocol.quantize`)."""
    try:
        return quantise(grid.logodds)
    except ValueError as exc:
        raise ProtocolError(str(exc), reason="value") from None


def _as_quantised(since: Grid | np.ndarray) -> np.ndarray:
    if isinstance(since, Grid):
        return quantise_grid(since)
    arr = np.asarray(since)
    if arr.dtype == np.int8:
        return arr
    try:
        return quantise(arr)
    except ValueError as exc:
        raise ProtocolError(str(exc), reason="value") from None


def encode_map(
    fleet: str,
    robot: str,
    version: int,
    grid: Grid,
    key: bytes | None = None,
    since: Grid | np.ndarray | None = None,
    base_version: int | None = None,
    max_message_bytes: int = 60_000,
    tile_size: int = DEFAULT_TILE_SIZE,
    indices: Collection[int] | None = None,
    lone_oversize: bool = False,
    first_epoch: int | None = None,
    final: bool = False,
) -> tuple[list[bytes], bytes]:
    """Encode one version of a robot's own map as tile messages and a manifest.

    Parameters
    ----------
    fleet, robot : ids (``[A-Za-z0-9_-]``, up to 64 characters).
    version : this map version, > every earlier version of ``robot``.
    grid : the local map; its log-odds (eq. (9)) are quantised to int8.
    key : fleet key; every message then carries an HMAC-SHA256.
    since : the map (Grid, int8 quantised array, or float log-odds) of an
        earlier version the receivers hold; only tiles changed since then are
        sent, as differences.  Ignored when its shape differs (a full update).
    base_version : the version ``since`` was.  With ``since``, the manifest is
        then a delta manifest: it lists only the changed tiles (bytes
        proportional to the change, not to the map), and receivers that do
        not hold ``base_version`` must fetch the full manifest (e.g. from a
        queryable, or wait for the full one to be re-announced).
    max_message_bytes : every tile message is smaller than this.
    tile_size : tile side, one of :data:`protocol.messages.TILE_SIZES`.
    indices : send these tiles, full (a queryable's answer to
        :meth:`MapReassembler.missing`); overrides ``since``.  Indices that
        hold no knowledge in this version are skipped: the manifest, which a
        queryable should send along, already tells the receiver they are empty.
    lone_oversize : let a tile that alone exceeds ``max_message_bytes`` travel
        in a message of its own rather than raise (packing into datagrams, see
        :func:`protocol.codec.encode_tiles`).
    first_epoch : the registration epoch of ``robot``'s first map version, carried by
        the manifest (:class:`protocol.messages.Manifest`); None leaves it out.
    final : mark the manifest as of ``robot``'s last version (:class:`Manifest`).

    Returns
    -------
    tile_messages : list of bytes, each one MapTiles message (may be empty
        when nothing changed since ``since``).
    manifest : bytes of the Manifest: every tile that holds knowledge, or the
        changed ones when ``since`` and ``base_version`` are given.
    """
    q = quantise_grid(grid)
    geometry = Geometry(grid.shape, grid.resolution, tuple(grid.origin), tile_size)
    checksums = manifest_checksums(q, geometry)
    manifest = Manifest(
        fleet, robot, version, geometry, checksums, first_epoch=first_epoch, final=final
    )
    base = None if since is None else _as_quantised(since)
    if base is not None and base.shape != q.shape:
        base, base_version = None, None
    if indices is not None:
        tiles = [full_tile(q, geometry, i) for i in sorted(set(indices) & set(checksums))]
        base_version = None
    elif base is None:
        tiles = [full_tile(q, geometry, i) for i in checksums]
        base_version = None
    else:
        check_quantised(base, geometry)
        tiles = [delta_tile(q, base, geometry, i) for i in changed_tiles(q, base, geometry)]
    if base is not None and base_version is not None:
        manifest = _delta_manifest(manifest, base, base_version)
    manifest_bytes = encode(manifest, key)
    if not tiles:
        return [], manifest_bytes
    msg = MapTiles(fleet, robot, version, geometry, tuple(tiles), base_version)
    return encode_tiles(msg, key, max_message_bytes, lone_oversize), manifest_bytes


def _delta_manifest(full: Manifest, base: np.ndarray, base_version: int) -> Manifest:
    """``full`` as a delta manifest against the quantised grid ``base`` of ``base_version``."""
    g = full.geometry
    before = manifest_checksums(base, g)
    changes = {i: crc for i, crc in full.checksums.items() if before.get(i) != crc}
    changes.update({i: zero_checksum(g, i) for i in before if i not in full.checksums})
    digest = manifest_digest(g, full.checksums)
    return Manifest(
        full.fleet, full.robot, full.version, g, changes, base_version, digest, full.first_epoch,
        full.final,
    )  # fmt: skip


#: Delta manifests a reassembler keeps while their base versions complete.
MAX_ORPHANS = 16


class MapReassembler:
    """Rebuilds one peer robot's map from its tile and manifest messages, in any order.

    Keeps, per robot, the tiles of the last complete version so that deltas
    apply and unchanged tiles need no transfer.  Stale versions are ignored;
    tiles that arrive before their manifest are buffered (bounded).

    Parameters
    ----------
    robot : the peer whose messages this reassembler accepts.
    fleet : if given, messages of another fleet are refused.
    limits : bounds the cells of tiles buffered ahead of their manifest.
    """

    def __init__(self, robot: str, fleet: str | None = None, limits: Limits = Limits()) -> None:  # noqa: B008
        self.robot = check_id(robot, "robot")
        self.fleet = None if fleet is None else check_id(fleet, "fleet")
        self.limits = limits
        #: Version of the last complete map, or None.
        self.version: int | None = None
        #: Its int8 cells (what the sender quantised), or None.
        self.quantised: np.ndarray | None = None
        #: The first epoch its manifest carried (:class:`Manifest`), or None.
        self.first_epoch: int | None = None
        #: Whether its manifest marked it its robot's last version (:class:`Manifest`).
        self.final = False
        #: Buffered tile messages dropped when their manifest arrived and contradicted them.
        self.dropped = 0
        self._manifest: Manifest | None = None  # full manifest being assembled
        self._base: Manifest | None = None  # full manifest of the complete version
        # Delta manifests whose base version is not complete yet, by version (bounded).
        self._orphans: dict[int, Manifest] = {}
        self._assembler: TileAssembler | None = None
        self._buffer: dict[int, list[MapTiles]] = {}
        self._buffered = 0  # cells held in _buffer

    @property
    def pending_version(self) -> int | None:
        """Version of the manifest being assembled, or None."""
        return None if self._manifest is None else self._manifest.version

    def missing(self) -> list[int]:
        """Tile indices to fetch, ascending.

        Those the pending manifest lacks; else every index while a delta manifest
        waits for a base version this receiver does not hold (which tiles exist is
        then unknown: fetch the full latest version); else none.
        """
        if self._manifest is not None and self._assembler is not None:
            return self._assembler.missing(self._manifest)
        if self._orphans:
            return list(range(self._orphans[max(self._orphans)].geometry.n_tiles))
        return []

    def feed(self, msg: Message) -> Grid | None:
        """Take one decoded message; return the complete grid when a version completes.

        Raises
        ------
        ProtocolError
            If ``msg`` is not a map message of this robot and fleet, contradicts
            the manifest of its version, a delta tile fails its checksum, or a
            delta manifest does not rebuild onto the held base version.
        """
        if not isinstance(msg, (MapTiles, Manifest)):
            raise ProtocolError(f"a {type(msg).__name__} is not a map message", reason="schema")
        if msg.robot != self.robot:
            raise ProtocolError(
                f"message of robot {msg.robot!r}, expected {self.robot!r}", reason="value"
            )
        if self.fleet is not None and msg.fleet != self.fleet:
            raise ProtocolError(
                f"message of fleet {msg.fleet!r}, expected {self.fleet!r}", reason="value"
            )
        if self.version is not None and msg.version <= self.version:
            return None
        if isinstance(msg, Manifest):
            return self._take_manifest(msg)
        pending = self.pending_version
        if pending is None or msg.version > pending:
            self._hold(msg)
            return None
        if msg.version < pending:
            return None
        self._apply(msg)
        return self._complete()

    def _take_manifest(self, manifest: Manifest) -> Grid | None:
        if manifest.is_delta:
            base = self._base
            if base is None or manifest.base_version != self.version:
                self._orphans[manifest.version] = manifest
                if len(self._orphans) > MAX_ORPHANS:
                    del self._orphans[min(self._orphans)]
                return None
            if (base.geometry.shape, base.geometry.tile_size) != (
                manifest.geometry.shape,
                manifest.geometry.tile_size,
            ):
                raise ProtocolError(
                    f"delta manifest {manifest.version} changes the map's shape", reason="value"
                )
            manifest = expand_manifest(manifest, base.checksums)
        current = self._manifest
        if current is not None:
            if manifest.version < current.version:
                return None
            if manifest.version == current.version:
                if manifest != current:
                    raise ProtocolError(
                        f"two different manifests for version {manifest.version}", reason="value"
                    )
                return self._complete()
        g = manifest.geometry
        if self._assembler is None or (
            (self._assembler.geometry.shape, self._assembler.geometry.tile_size)
            != (g.shape, g.tile_size)
        ):
            self._assembler = TileAssembler(g)
        self._manifest = manifest
        for version in [v for v in self._buffer if v <= manifest.version]:
            held = self._buffer.pop(version)
            self._buffered -= sum(map(_cells, held))
            if version == manifest.version:
                for msg in held:
                    try:
                        self._apply(msg)
                    except ProtocolError:
                        # Raising here would lose the manifest; the bad tiles stay missing.
                        self.dropped += 1
        return self._complete()

    def _hold(self, msg: MapTiles) -> None:
        """Buffer tiles of a version whose manifest has not arrived; oldest are dropped first."""
        self._buffer.setdefault(msg.version, []).append(msg)
        self._buffered += _cells(msg)
        while self._buffered > self.limits.max_buffered_cells:
            oldest = min(self._buffer)
            self._buffered -= _cells(self._buffer[oldest].pop(0))
            if not self._buffer[oldest]:
                del self._buffer[oldest]

    def _apply(self, msg: MapTiles) -> None:
        manifest, assembler = self._manifest, self._assembler
        assert manifest is not None and assembler is not None
        g = msg.geometry
        if (g.shape, g.tile_size) != (manifest.geometry.shape, manifest.geometry.tile_size):
            raise ProtocolError(
                f"version {msg.version} tiles do not fit the manifest's shape", reason="value"
            )
        for tile in msg.tiles:
            if manifest.checksums.get(tile.index) != tile.checksum:
                raise ProtocolError(
                    f"tile {tile.index} of version {msg.version} is not the manifest's",
                    reason="value",
                )
        for tile in msg.tiles:
            # A delta whose base we lack stays missing; the agent fetches it in full.
            if not assembler.holds(tile.index, tile.checksum) and assembler.can_apply(tile):
                assembler.add(tile)

    def _complete(self) -> Grid | None:
        manifest, assembler = self._manifest, self._assembler
        if manifest is None or assembler is None or assembler.missing(manifest):
            return None
        q = assembler.assemble(manifest)
        assembler.forget(manifest.checksums)
        q.flags.writeable = False
        self.version, self.quantised, self._manifest = manifest.version, q, None
        self.first_epoch, self.final = manifest.first_epoch, manifest.final
        self._base = manifest
        g = manifest.geometry
        grid = Grid(dequantise(q), g.resolution, g.origin)
        self._orphans = {v: m for v, m in self._orphans.items() if v > manifest.version}
        waiting = [m for m in self._orphans.values() if m.base_version == manifest.version]
        if waiting:
            # A delta manifest that waited for this version: take it now.
            del self._orphans[waiting[0].version]
            return self._take_manifest(waiting[0]) or grid
        return grid


def _cells(msg: MapTiles) -> int:
    return sum(t.cells.size for t in msg.tiles)
