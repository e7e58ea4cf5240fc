"""The agent's thin adapter over :mod:`protocol`: own versions out, peers' maps and links in.

What the agent stores as its own map is what its peers will decode: the log-odds after
the int8 round trip (:func:`on_the_wire`).  Otherwise the agent and its peers would fuse
slightly different inputs and their global maps would differ (fleet invariant 2).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from agent.keys import FleetKeys
from agent.links import LinkRecord, epoch_of
from pgvd.grid import Grid
from pgvd.uncertainty import check_covariance
from protocol import (
    Limits,
    Link,
    LinkTrust,
    Manifest,
    MapReassembler,
    MapTiles,
    Message,
    ProtocolError,
    TileFetch,
    decode,
    dequantise,
    encode,
    encode_map,
    peek_map,
    quantise_grid,
)
from protocol.messages import DEFAULT_TILE_SIZE

MAP_MESSAGES = (MapTiles, Manifest)
#: Peers tracked at most: a flood of invented robot ids cannot exhaust memory.
MAX_PEERS = 256

__all__ = ["MAP_MESSAGES", "Inbound", "Link", "Message", "Outbound", "encode_link", "link_record"]


def on_the_wire(grid: Grid) -> Grid:
    """``grid`` as a peer decodes it: log-odds quantised to int8 and back."""
    return Grid(dequantise(quantise_grid(grid)), grid.resolution, tuple(grid.origin))


#: Tile messages published best-effort are packed to this many bytes, so that each rides one
#: UDP datagram of a 1500-byte MTU (with Zenoh's framing, see ``zenoh_config.TILE_BATCH_BYTES``):
#: a message above a few KB rides IP fragmentation, and one lost fragment loses all of it.
DATAGRAM_BYTES = 1200
#: Smaller tiles for datagrams: most 64x64 tiles of a real map compress under DATAGRAM_BYTES.
DATAGRAM_TILE_SIZE = 64
#: Tiles per second the ``latest`` queryable encodes for fetches that name tiles. Beyond it a
#: fetch gets the whole map, whose bytes are prepared in advance: a stranger's flood of fetches
#: then costs bandwidth it could take anyway, not CPU on Zenoh's callback threads.
FETCH_TILES_PER_SECOND = 2048


class TileBudget:
    """A token bucket of tiles: ``rate`` per second, at most one second's worth saved."""

    def __init__(self, rate: float, now: float | None = None) -> None:
        self.rate = rate
        self._tokens = rate
        self._at = time.monotonic() if now is None else now
        self._lock = threading.Lock()  # queryable callbacks may run on several threads

    def take(self, n: int, now: float | None = None) -> bool:
        """Spend ``n`` tiles if the bucket holds them."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._tokens = min(self.rate, self._tokens + (now - self._at) * self.rate)
            self._at = now
            if n > self._tokens:
                return False
            self._tokens -= n
            return True


@dataclass(frozen=True)
class Prepared:
    """One own version encoded: ``published`` goes out on the tiles and manifest keys, ``whole``
    (every tile, default message size) answers the ``latest`` queryable. Each is
    ``(tile messages, manifest)``; both manifests carry ``first_epoch`` and, for the
    source's last version, the ``final`` mark."""

    version: int
    grid: Grid
    published: tuple[list[bytes], bytes]
    whole: tuple[list[bytes], bytes]
    first_epoch: int | None = None
    final: bool = False


class Received(NamedTuple):
    """A peer's version completed: its number, grid, the robot's first epoch (None when
    the manifest did not say) and whether the manifest marked it the robot's last."""

    version: int
    grid: Grid
    first_epoch: int | None
    final: bool


class Outbound:
    """Encodes the own map's versions: deltas to publish, and the full latest for queries.

    With ``datagrams`` the published tile messages are packed for best-effort UDP
    (:data:`DATAGRAM_BYTES`); the full latest version, which queries fetch over a reliable
    link, keeps the default message size.
    """

    def __init__(self, fleet: str, robot: str, key: bytes | None, datagrams: bool = False) -> None:
        self.fleet, self.robot, self.key = fleet, robot, key
        self.datagrams = datagrams
        self._tile_size = DATAGRAM_TILE_SIZE if datagrams else DEFAULT_TILE_SIZE
        self._latest: tuple[int, list[bytes], bytes, Grid] | None = None
        self.fetch_budget = TileBudget(FETCH_TILES_PER_SECOND)

    def encode(
        self,
        version: int,
        grid: Grid,
        previous: tuple[int, Grid] | None,
        first_epoch: int | None = None,
        final: bool = False,
    ) -> Prepared:
        """``version`` encoded, to publish (a delta against ``previous`` if given) and to serve;
        its manifests carry the robot's ``first_epoch`` (the merged frame's anchor is chosen
        by it, :func:`agent.globalmap.anchor_rank`) and, with ``final``, the mark of the
        source's last version (:class:`protocol.messages.Manifest`).

        Nothing changes until :meth:`install`: a version that is not yet persisted must not be
        served to a fetch.
        """
        marks = {"first_epoch": first_epoch, "final": final}
        full = self._encode(version, grid, None, False, **marks)
        if previous is None and not self.datagrams:
            return Prepared(version, grid, full, full, first_epoch, final)
        published = self._encode(version, grid, previous, self.datagrams, **marks)
        return Prepared(version, grid, published, full, first_epoch, final)

    def install(self, prepared: Prepared) -> None:
        """Serve ``prepared`` as the latest version from now on."""
        self._latest = (prepared.version, *prepared.whole, prepared.grid)

    def prepare(
        self,
        version: int,
        grid: Grid,
        previous: tuple[int, Grid] | None,
        first_epoch: int | None = None,
    ) -> tuple[list[bytes], bytes]:
        """:meth:`encode` and :meth:`install` ``version``; its tile messages and manifest."""
        prepared = self.encode(version, grid, previous, first_epoch)
        self.install(prepared)
        return prepared.published

    def _encode(
        self,
        version: int,
        grid: Grid,
        previous: tuple[int, Grid] | None,
        packed: bool,
        indices: frozenset[int] | None = None,
        first_epoch: int | None = None,
        final: bool = False,
    ) -> tuple[list[bytes], bytes]:
        since = {} if previous is None else {"since": previous[1], "base_version": previous[0]}
        packing = {"max_message_bytes": DATAGRAM_BYTES, "lone_oversize": True} if packed else {}
        return encode_map(
            self.fleet,
            self.robot,
            version,
            grid,
            self.key,
            tile_size=self._tile_size,
            indices=indices,
            first_epoch=first_epoch,
            final=final,
            **since,
            **packing,
        )

    def manifest(self) -> bytes | None:
        return None if self._latest is None else self._latest[2]

    def latest_replies(
        self, keys: FleetKeys, fetch: TileFetch | None = None
    ) -> list[tuple[str, bytes]]:
        """The answer to a fetch, each message under its own concrete key, manifest last.

        The tiles ``fetch`` names if it asks for the latest version and the fetch budget
        allows, else the whole latest version (the asker then learns of the newer one).
        """
        latest = self._latest  # one read: the main thread may replace it meanwhile
        if latest is None:
            return []
        version, tiles, manifest, grid = latest
        if (
            fetch is not None
            and fetch.version == version
            and self.fetch_budget.take(len(fetch.indices))
        ):
            tiles = self._encode(version, grid, None, packed=False, indices=fetch.indices)[0]
        out = [(keys.latest_reply(self.robot, version, f"t{i}"), t) for i, t in enumerate(tiles)]
        out.append((keys.latest_reply(self.robot, version, "m"), manifest))
        return out


class Inbound:
    """Decodes payloads and reassembles each peer's map (one reassembler per peer)."""

    def __init__(self, fleet: str, key: bytes | None, limits: Limits | None = None) -> None:
        self.fleet, self.key = fleet, key
        self.limits = limits or Limits()
        self._reassemblers: dict[str, MapReassembler] = {}

    def decode(self, data: bytes) -> Message:
        """Decode and authenticate one payload; raises only ProtocolError."""
        return decode(data, self.key, self.limits)

    def peek(self, data: bytes) -> tuple[bool, str, int] | None:
        """``(is_tiles, robot, version)`` of an authentic map message, or None
        (:func:`protocol.codec.peek_map`: cheap, nothing is decompressed)."""
        return peek_map(data, self.key, self.limits)

    def feed(self, msg: MapTiles | Manifest) -> Received | None:
        """Feed a map message; :class:`Received` when a version completes.

        Raises ProtocolError for a manifest whose first epoch is newer than its version's.
        """
        if isinstance(msg, Manifest) and (msg.first_epoch or 0) > epoch_of(msg.version):
            raise ProtocolError(
                f"first epoch {msg.first_epoch} is newer than version {msg.version}'s",
                reason="value",
            )
        reasm = self._reassemblers.get(msg.robot)
        if reasm is None:
            if len(self._reassemblers) >= MAX_PEERS:
                raise ProtocolError(f"more than {MAX_PEERS} robots in the fleet", reason="limit")
            reasm = self._reassemblers[msg.robot] = MapReassembler(
                msg.robot, self.fleet, self.limits
            )
        grid = reasm.feed(msg)
        if grid is None:
            return None
        assert reasm.version is not None
        return Received(reasm.version, grid, reasm.first_epoch, reasm.final)

    def wanted(self, robot: str) -> tuple[int, list[int]] | None:
        """The version of ``robot`` being assembled and the tiles it lacks, if a manifest waits."""
        reasm = self._reassemblers.get(robot)
        if reasm is None or reasm.pending_version is None:
            return None
        return reasm.pending_version, reasm.missing()

    def forget(self, robot: str) -> None:
        """Drop ``robot``'s reassembly state (the robot left and is forgotten)."""
        self._reassemblers.pop(robot, None)

    def incomplete(self, robot: str) -> bool:
        """True if a manifest of ``robot`` waits for tiles that are not held."""
        reasm = self._reassemblers.get(robot)
        return reasm is not None and bool(reasm.missing())


def encode_link(fleet: str, rec: LinkRecord, key: bytes | None) -> bytes:
    msg = Link(
        fleet,
        rec.decided_by,
        rec.a,
        rec.b,
        rec.version_a,
        rec.version_b,
        rec.accepted,
        rec.matrix.tolist(),
        rec.covariance.tolist(),
        rec.score,
        LinkTrust(
            rec.state,
            rec.margin,
            rec.first_margin,
            rec.reason,
            rec.first_a,
            rec.first_b,
            rec.holds,
            rec.revision,
        ),
    )
    return encode(msg, key)


def link_record(msg: Link) -> LinkRecord:
    """The cached form of a received link; ``ValueError`` if it breaks the agent's rules."""
    m = np.asarray(msg.matrix, dtype=np.float64)
    if abs(abs(np.linalg.det(m[:2, :2])) - 1.0) > 1e-3 or np.any(m[2] != (0.0, 0.0, 1.0)):
        raise ValueError("link matrix is not rigid")
    covariance = np.asarray(msg.covariance, dtype=np.float64)
    if msg.accepted:
        # An accepted link's covariance is composed along chains in every global-map rebuild.
        covariance = check_covariance(covariance)
    return LinkRecord(
        msg.robot_a,
        msg.version_a,
        msg.robot_b,
        msg.version_b,
        msg.accepted,
        m,
        covariance,
        msg.score,
        msg.decided_by,
        **_lifecycle(msg.trust),
    )


def _lifecycle(trust: LinkTrust | None) -> dict[str, object]:
    """A received link's lifecycle as :class:`agent.links.LinkRecord` fields; a link of the
    older format has none, and its record reads its state from its outcome."""
    if trust is None:
        return {}
    return {
        "state": trust.state,
        "margin": trust.margin,
        "first_margin": trust.first_margin,
        "reason": trust.reason,
        "first_a": trust.first_version_a,
        "first_b": trust.first_version_b,
        "holds": trust.holds,
        "revision": trust.revision,
    }
