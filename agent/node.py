"""The fleet core: one robot's agent as a state machine, with no Zenoh, clock, thread or file.

As h11 splits its ``Connection`` from the socket, :class:`FleetNode` holds every rule of the
agent and its host (:class:`agent.daemon.Agent`) only moves bytes and time. The host feeds in

- :meth:`FleetNode.on_message` -- a payload that arrived on a key (pushed, or a fetch's reply),
  or :meth:`FleetNode.on_decoded` -- the same once :meth:`FleetNode.read` decoded it;
- :meth:`FleetNode.on_alive` -- a robot's liveliness token appeared or went away;
- :meth:`FleetNode.on_source` -- the robot's own source produced a new map;
- :meth:`FleetNode.tick` -- time passed;
- :meth:`FleetNode.on_persisted`, :meth:`FleetNode.on_link`, :meth:`FleetNode.on_global` --
  the state directory and the fusion worker (:mod:`agent.worker`) report back,

each with the time as an :class:`Instant`, and carries out the actions each call returns
(:mod:`agent.actions`), in order. The rules:

- admission: a message is decoded and authenticated (:mod:`protocol`), then dropped, with a
  reason, if it is of another fleet, of a kind nobody publishes, under another robot's key,
  under this robot's own id, or older than the version held; a version held already is a
  re-announce and ignored;
- reassembly and fetching: tiles and manifests complete a peer's version; an incomplete one is
  fetched from the peer's ``latest`` queryable once tiles in flight had time to come
  (:mod:`agent.fetching`), and a robot that joins is fetched at once with its links;
- own-map publication: the source's map becomes a new version when the change gate says so,
  in a new registration epoch when it changed enough (:mod:`agent.links`); the version is
  persisted before it is published or served, so a peer never holds a version this agent could
  lose;
- link bookkeeping: links received or decided here are cached, published and persisted;
- status: the JSON that ``pgvd status`` and ``status.json`` show.

Calls must not overlap (the host serialises them); :meth:`FleetNode.read` and the
``answer_*`` methods read only thread-safe state and may run on other threads meanwhile.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from agent import wire
from agent.actions import (
    Action,
    Drop,
    Fetch,
    ForgetMap,
    PersistGlobal,
    PersistLinks,
    PersistMap,
    Publish,
    Register,
    Reply,
    WriteStatus,
)
from agent.book import FleetBook, next_version
from agent.counters import Counters
from agent.fetching import MIN_INTERVAL_S, FetchSchedule
from agent.globalmap import component_of
from agent.keys import FleetKeys
from agent.links import LinkRecord, epoch_of
from agent.sources import ChangeGate, epoch_due
from agent.state import StoredMap
from agent.status import (
    HostFacts,
    component_json,
    global_json,
    globalmap_line,
    link_states,
    links_json,
    robots_json,
    versions_of,
)
from pgvd.grid import Grid
from protocol.auth import seal
from protocol.errors import ProtocolError
from protocol.fetch import fetch_parameters, parse_fetch

if TYPE_CHECKING:  # the worker's thread is the host's business, not the core's
    from agent.globalmap import Component
    from agent.worker import GlobalState

log = logging.getLogger("pgvd.agent")


@dataclass(frozen=True)
class Instant:
    """One reading of both clocks, in seconds.

    ``mono`` (never jumps) times fetches, the change gate and periods; ``wall`` stamps versions
    (their epoch must be newer than any before a restart) and the status.
    """

    mono: float
    wall: float


@dataclass(frozen=True)
class NodeOptions:
    """The core's part of ``pgvd agent``'s options (:class:`agent.daemon.AgentOptions`).

    Attributes
    ----------
    robot, fleet : this robot's id and its fleet's name (key chunks, :func:`agent.keys.check_name`).
    key : the fleet key that authenticates every message, or None for an open fleet.
    datagrams : pack published tiles for best-effort UDP (:data:`agent.wire.DATAGRAM_BYTES`).
    announce_period : seconds between re-announcements of the own manifest.
    status_period : seconds between status writes (a new global map writes one at once).
    min_change, min_interval : the change gate (:class:`agent.sources.ChangeGate`): the fraction
        of known cells that must change class, and the seconds between two own versions.
    epoch_change : the fraction of known cells changed since an epoch began that starts a new
        registration epoch (:func:`agent.sources.epoch_due`).
    forget_after : seconds after a robot left (its liveliness token went away) before its
        map, links and reassembly state are dropped, so that what an agent holds is bounded
        by the robots present, not by every robot it has ever seen.
    """

    robot: str
    fleet: str = "default"
    key: bytes | None = None
    datagrams: bool = False
    announce_period: float = 2.0
    status_period: float = 1.0
    min_change: float = 0.05
    min_interval: float = 1.0
    epoch_change: float = 0.15
    forget_after: float = 300.0


class FleetNode:
    """One robot's view of its fleet and the rules that move it (see the module docstring).

    Parameters
    ----------
    opts : NodeOptions
        The robot, its fleet and the core's periods and thresholds.
    now : Instant
        The time the node starts at (the change gate counts its first interval from it).
    """

    def __init__(self, opts: NodeOptions, now: Instant) -> None:
        self.opts = opts
        self.me = opts.robot
        self.keys = FleetKeys(opts.fleet)
        self.counters = Counters()
        #: Shared with the fusion worker, which reads maps and adds the links it decides.
        self.book = FleetBook()
        self.inbound = wire.Inbound(opts.fleet, opts.key)
        self.outbound = wire.Outbound(opts.fleet, self.me, opts.key, datagrams=opts.datagrams)
        self.fetches = FetchSchedule()
        self.gate = ChangeGate(opts.min_change, opts.min_interval)
        self.gate.reset(None, now.mono)
        self.alive: dict[str, bool] = {}
        self._left: dict[str, float] = {}  # robot -> monotonic time its token went away
        self.started = now.wall
        self.last_update: float | None = None
        self.settled_at: float | None = None
        self._global: GlobalState | None = None
        self._own_digest: str | None = None
        self._links_dirty = False
        self._pending: tuple[Grid, bool, dict[str, object]] | None = None
        self._unsaved: wire.Prepared | None = None
        self._epoch_base: Grid | None = None  # own map when the current epoch began
        # The epoch of this robot's first version: its age, by which merged frames are
        # anchored (agent.globalmap.anchor_rank); None until the first version.
        self._first_epoch: int | None = None
        self._next_announce = self._next_status = -float("inf")
        self._status_due = False

    def restore(
        self, maps: Mapping[str, StoredMap], links: Iterable[LinkRecord], now: Instant
    ) -> None:
        """Take back what the state directory held; the own map is served again at once.

        A peer's map persisted without its first epoch (a file of an older agent) is left to
        be fetched again: every agent must read the same first epoch with a version.  The
        own map's is its version's epoch then, the oldest this robot can still vouch for.
        """
        for robot, stored in maps.items():
            first = stored.first_epoch
            if robot == self.me:
                first = epoch_of(stored.version) if first is None else first
                self._first_epoch = first
            elif first is None:
                continue
            # Own maps are persisted as the source holds them (to resume integrating).
            grid = wire.on_the_wire(stored.grid) if robot == self.me else stored.grid
            self.book.put_map(robot, stored.version, grid, first)
            # Gone until its liveliness token says otherwise (the membership history reports
            # every robot present): a robot that left while this agent was down is forgotten
            # on the same bound as everywhere else, not kept for good in this agent's global
            # map alone.
            self._absent_until_seen((robot,), now)
        for rec in links:
            self.book.add_link(rec)
            self._absent_until_seen(rec.pair, now)
        own = self.book.map_of(self.me)
        if own is not None:
            self.outbound.prepare(own[0], own[1], previous=None, first_epoch=self._first_epoch)
            self.gate.reset(own[1], now.mono)
            # The epoch goes on from the last version held: with no base, the first version
            # after every restart began an epoch, and all of this robot's links were
            # registered again. The base is the map the epoch began with, not saved; the
            # last version stands for it, so the next epoch begins a little later.
            self._epoch_base = own[1]

    # ------------------------------------------------------------------ inputs

    def on_message(self, key: str, payload: bytes, now: Instant) -> list[Action]:
        """A payload that came on ``key``: a pushed message or a fetch's reply."""
        msg = self.read(key, payload)
        return [msg] if isinstance(msg, Drop) else self.on_decoded(key, msg, now)

    def read(self, key: str, payload: bytes) -> wire.Message | Drop:
        """``payload`` decoded and authenticated, or the Drop that refuses it.

        Any thread, overlapping other calls: it reads only the fleet key and limits. A host
        decodes on a thread of its own, then hands the message to :meth:`on_decoded`.
        """
        try:
            return self.inbound.decode(payload)
        except ProtocolError as exc:  # counted by what it broke: framing, auth, schema, ...
            return Drop(exc.reason, self.keys.robot_of(key) or key, str(exc))

    def on_decoded(self, key: str, msg: wire.Message, now: Instant) -> list[Action]:
        """A message :meth:`read` from a payload that came on ``key``."""
        sender = self.keys.robot_of(key) or key
        if msg.fleet != self.opts.fleet:
            return [Drop("foreign_fleet", sender, f"fleet {msg.fleet!r}")]
        if isinstance(msg, wire.Link):
            return self._admit_link(msg, sender, now)
        if not isinstance(msg, wire.MAP_MESSAGES):
            return [Drop("unexpected_kind", sender, type(msg).__name__)]
        if sender != msg.robot:
            return [Drop("key_mismatch", sender, f"key {key} carries robot {msg.robot}")]
        if msg.robot == self.me:
            return [Drop("own_robot_id", sender, "a peer publishes under this robot's id")]
        held = self.book.version(msg.robot)
        if held is not None and msg.version < held:
            return [Drop("stale_version", msg.robot, f"v{msg.version} < held v{held}")]
        if held is not None and msg.version == held:
            return []  # a re-announce or a duplicate reply: nothing new
        return self._reassemble(msg, now)

    def on_alive(self, robot: str, alive: bool, now: Instant) -> list[Action]:
        """``robot``'s liveliness token appeared (``alive``) or went away."""
        if robot == self.me:
            return []
        was = self.alive.get(robot)
        self.alive[robot] = alive
        self.book.set_alive({self.me} | {r for r, up in self.alive.items() if up})
        actions: list[Action] = [Register()]
        if alive:
            self._left.pop(robot, None)
        else:
            self._left.setdefault(robot, now.mono)
        if alive and not was:
            log.info("robot %s joined", robot)
            actions += self._fetch(robot, now, links=True)
        elif not alive and was:
            log.info("robot %s left", robot)
        return actions

    def on_source(
        self,
        grid: Grid,
        now: Instant,
        final: bool = False,
        resume: Mapping[str, object] | None = None,
    ) -> list[Action]:
        """The own source's map changed: publish it when the change gate says it is due.

        ``final`` marks the source's last map: published whatever the gate says, in a new
        registration epoch, its manifest marked final (:class:`protocol.messages.Manifest`)
        so that peers confirm a decision on it without waiting for a newer version
        (:mod:`agent.trust`); ``resume`` is what the source needs to continue from this map
        after a restart.
        """
        self._pending = (grid, final, dict(resume or {}))
        return self._publish_pending(now)

    def on_persisted(self, robot: str, version: int, now: Instant) -> list[Action]:
        """``robot``'s map ``version`` is on disk; the own version waiting for it goes out."""
        unsaved = self._unsaved
        if robot != self.me or unsaved is None or unsaved.version != version:
            return []
        self._unsaved = None
        self.outbound.install(unsaved)
        self.book.put_map(self.me, version, unsaved.grid, unsaved.first_epoch, unsaved.final)
        self.last_update = now.wall
        tiles, manifest = unsaved.published
        key = self.keys.tiles(self.me)
        actions: list[Action] = [Register()]
        for i, data in enumerate(tiles):  # a crash test stops after the first: mid-publication
            actions.append(Publish(key, data, "tiles-send" if i == 0 else None))
        actions.append(Publish(self.keys.manifest(self.me), manifest))
        self.counters.add("versions_published")
        log.debug("published own map v%d (%d tile messages)", version, len(tiles))
        return actions

    def on_link(self, rec: LinkRecord, now: Instant) -> list[Action]:
        """The fusion worker decided ``rec`` (and cached it): publish it."""
        self._absent_until_seen(rec.pair, now)  # a robot forgotten while it was registered
        self._links_dirty = True
        self.counters.add("links_published")
        data = wire.encode_link(self.opts.fleet, rec, self.opts.key)
        return [Publish(self.keys.link(rec.a, rec.b), data)]

    def on_global(self, state: GlobalState, now: Instant) -> list[Action]:
        """The fusion worker rebuilt the global maps: write this robot's if it changed."""
        self._global = state
        actions: list[Action] = []
        own = component_of(state.components, self.me)
        if own is not None and own.digest != self._own_digest:
            self._own_digest = own.digest
            actions.append(PersistGlobal(own))
            log.info("%s settled=%s", globalmap_line(own), str(state.settled).lower())
        if state.settled and self.settled_at is None:
            self.settled_at = now.wall
        elif not state.settled:
            self.settled_at = None
        self._status_due = True
        return actions

    def tick(self, now: Instant) -> list[Action]:
        """Time passed: publish a gated own map, fetch what is due, re-announce, write status."""
        actions = self._publish_pending(now)
        for robot, left in sorted(self._left.items()):
            if now.mono - left >= self.opts.forget_after:
                actions += self._forget(robot)
        for robot in self.fetches.pop_due(now.mono):
            actions += self._fetch(robot, now, links=False)
        if now.mono >= self._next_announce:
            self._next_announce = now.mono + self.opts.announce_period
            manifest = self.outbound.manifest()  # late joiners and lost manifests catch up
            if manifest is not None:
                actions.append(Publish(self.keys.manifest(self.me), manifest))
        if now.mono >= self._next_status or self._status_due:
            self._next_status = now.mono + self.opts.status_period
            self._status_due = False
            actions += self.flush()
        return actions

    def flush(self) -> list[Action]:
        """Persist the links if they changed, and write the status (also at shutdown)."""
        actions: list[Action] = []
        if self._links_dirty:
            self._links_dirty = False
            actions.append(PersistLinks(tuple(self.book.link_candidates())))
        actions.append(WriteStatus())
        return actions

    # ---------------------------------------------------- queries (any thread)

    def answer_latest(self, version: str | None, tiles: str | None) -> list[Action]:
        """Replies to a fetch of this robot's latest map (``v`` and ``tiles`` parameters)."""
        try:
            fetch = parse_fetch(version, tiles)
        except ProtocolError as exc:
            return [Drop(exc.reason, "query", f"fetch: {exc}")]
        return [Reply(k, data) for k, data in self.outbound.latest_replies(self.keys, fetch)]

    def answer_links(self) -> list[Action]:
        """Replies to a query of the links held: every candidate, one key each."""
        fleet, key = self.opts.fleet, self.opts.key
        return [
            Reply(self.keys.links_reply(self.me, i), wire.encode_link(fleet, rec, key))
            for i, rec in enumerate(self.book.link_candidates())
        ]

    def answer_status(self, payload: bytes) -> Reply:
        """The reply carrying the status JSON ``payload``, with the fleet MAC if keyed."""
        mac = None if self.opts.key is None else seal(payload, self.opts.key)
        return Reply(self.keys.status(self.me), payload, mac)

    def global_component(self) -> Component | None:
        """The last rebuilt component holding this robot (its global map), or None yet."""
        glob = self._global
        return None if glob is None else component_of(glob.components, self.me)

    # ----------------------------------------------------------------- status

    def _source_json(self, source: Mapping[str, object]) -> dict[str, object]:
        """The source's status entry, ``done`` only once its last map is published: the
        source reads done when its last scan is in, but that map waits for the change gate
        and for its persistence, and a reader that saw ``done`` beside the version before
        it took that one for the last (the demo's and benches' agreement did, and stopped
        a fleet before its final maps were decided)."""
        waiting = self._pending is not None or self._unsaved is not None
        return {**source, "done": bool(source.get("done")) and not waiting}

    def status(self, now: Instant, host: HostFacts) -> dict[str, object]:
        """The JSON status: robots, versions, links, components, traffic, drops."""
        glob = self._global
        versions = self.book.versions()
        comps = [] if glob is None else glob.components
        counters = self.counters.snapshot()
        links = self.book.links()
        return {
            "robot": self.me,
            "fleet": self.opts.fleet,
            "pid": host.pid,
            "time": now.wall,
            "started": self.started,
            "source": self._source_json(host.source),
            "own_version": versions.get(self.me),
            "last_update": self.last_update,
            "robots": robots_json(self.me, versions, self.alive),
            "links": links_json(links, versions),
            "link_states": link_states(links, versions),
            "components": [component_json(c) for c in comps],
            "global": global_json(component_of(comps, self.me)),
            "settled": bool(glob and glob.settled and versions_of(comps) == versions),
            "settled_at": self.settled_at,
            "merges": host.merges,
            "merge_seconds": round(host.merge_seconds, 3),
            "bytes_sent": counters["counts"].get("bytes_sent", 0),
            "bytes_received": counters["counts"].get("bytes_received", 0),
            "counts": counters["counts"],
            "drops": counters["drops"],
            "inbox": {"messages": host.inbox_messages, "bytes": host.inbox_bytes},
        }

    # ---------------------------------------------------------------- helpers

    def _forget(self, robot: str) -> list[Action]:
        """Drop a robot gone for ``forget_after`` s: its map, links, fetches, reassembly."""
        log.info("robot %s forgotten (gone for %.0f s)", robot, self.opts.forget_after)
        del self._left[robot]
        self.alive.pop(robot, None)
        self.book.set_alive({self.me} | {r for r, up in self.alive.items() if up})
        self.book.forget(robot)
        self.inbound.forget(robot)
        self.fetches.forget(robot)
        self._links_dirty = True
        self.counters.add("robots_forgotten")
        return [ForgetMap(robot), Register()]

    def _absent_until_seen(self, robots: Iterable[str], now: Instant) -> None:
        """Each of ``robots`` that is not present counts as gone from now on.

        Held maps and links of robots this agent never saw leave (a peer still held them
        when this agent joined, or the worker registered one after it was forgotten) were
        kept for good, persisted and served to the next joiner: links circulated of robots
        nobody had. They are forgotten on the bound of any robot that left, unless its
        liveliness token appears meanwhile.
        """
        for robot in robots:
            if robot != self.me and not self.alive.get(robot):
                self._left.setdefault(robot, now.mono)

    def _admit_link(self, msg: wire.Link, sender: str, now: Instant) -> list[Action]:
        try:
            rec = wire.link_record(msg)
        except ValueError as exc:
            return [Drop("bad_link", sender, str(exc))]
        if not self.book.add_link(rec):
            return []
        self._absent_until_seen(rec.pair, now)
        self.counters.add("links_received")
        self._links_dirty = True
        return [Register()]

    def _reassemble(self, msg: wire.MapTiles | wire.Manifest, now: Instant) -> list[Action]:
        try:
            done = self.inbound.feed(msg)
        except ProtocolError as exc:  # e.g. a tile that contradicts its manifest: value
            self.fetches.later(msg.robot, now.mono)
            return [Drop(exc.reason, msg.robot, str(exc))]
        if done is None:
            if self.inbound.incomplete(msg.robot):
                self.fetches.later(msg.robot, now.mono)  # tiles may still be in flight
            return []
        version, grid, first, final = done
        if not self.book.put_map(msg.robot, version, grid, first, final):
            return []
        self.counters.add("maps_received")
        self.fetches.cancel(msg.robot)
        log.debug("map %s v%d received (%dx%d)", msg.robot, version, *grid.shape)
        return [PersistMap(msg.robot, StoredMap(version, grid, first_epoch=first)), Register()]

    def _publish_pending(self, now: Instant) -> list[Action]:
        """Encode the source's map as the next own version if the gate says it is due."""
        if self._pending is None or self._unsaved is not None:
            return []
        grid, final, resume = self._pending
        if not self.gate.due(grid, now.mono, final=final):
            return []
        self._pending = None
        held = self.book.map_of(self.me)
        try:
            sent = wire.on_the_wire(grid)
            # A source's last map always starts an epoch: a pair rejected on an early
            # version of this epoch is decided once more on the final maps (a candidate is
            # re-checked at every version anyway).
            new_epoch = final or epoch_due(self._epoch_base, sent, self.opts.epoch_change)
            version = next_version(None if held is None else held[0], now.wall, new_epoch)
            # A robot's first version fixes its age for good (persisted with every version).
            first = epoch_of(version) if self._first_epoch is None else self._first_epoch
            self._unsaved = self.outbound.encode(version, sent, held, first, final)
        except ProtocolError as exc:  # e.g. a map beyond the wire's limits: keep serving
            return [Drop("own_map_unencodable", self.me, str(exc))]
        self._first_epoch = first
        if new_epoch:
            self._epoch_base = sent
            self.counters.add("epochs")  # the bench counts registrations per epoch
        # Persisted first, published by on_persisted: a peer never holds a version we could lose.
        stored = StoredMap(version, grid, resume, first)
        return [PersistMap(self.me, stored, point="state-write")]

    def _fetch(self, robot: str, now: Instant, links: bool) -> list[Action]:
        """Query ``robot``'s latest map (only the tiles missing, when few), and its links."""
        if not links and not self.fetches.allows(robot, now.mono):
            self.fetches.later(robot, now.mono, MIN_INTERVAL_S)
            return []
        self.fetches.sent(robot, now.mono)
        self.counters.add("fetches")
        wanted = self.inbound.wanted(robot)
        params = None if wanted is None else fetch_parameters(*wanted)
        if params is not None:
            self.counters.add("tile_fetches")
        actions: list[Action] = [Fetch(self.keys.latest(robot), params)]
        if links:
            actions.append(Fetch(self.keys.links(robot)))
        return actions
